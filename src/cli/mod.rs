pub mod raycast;

pub fn main() -> anyhow::Result<()> {
    Ok(())
}
