//! `gs4city view`: serve a finished run to the browser on 127.0.0.1 (docs/view.md).
use std::io::Write;
use std::path::PathBuf;

use anyhow::Context;
use clap::Args;

use crate::layout::Mode;

#[derive(Debug, Args)]
pub struct ViewArgs {
    /// A finished run folder (`gs4city run --scene S --out R`).
    #[arg(value_name = "R")]
    pub run: PathBuf,
    /// The scene folder the run was made from; default: the one recorded in R/run.json.
    #[arg(long, value_name = "DIR")]
    pub scene: Option<PathBuf>,
    /// Which per-Gaussian labels: `vote` (R/lift) or `learned` (R/train); default: learned when
    /// R/train/gaussians.npy exists (as `gs4city query`).
    #[arg(long)]
    pub mode: Option<Mode>,
    /// Port on 127.0.0.1 (0: a free one; the URL is printed).
    #[arg(long, default_value_t = 8765)]
    pub port: u16,
    /// The page's splat budget: a run of more Gaussians is drawn as a coarse set of at most
    /// this many splats (merged as the 3D Tiles export's inner tiles, docs/view.md).
    #[arg(long, default_value_t = crate::view::MAX_SPLATS)]
    pub max_splats: usize,
    /// Open the page in the desktop's browser (xdg-open).
    #[arg(long)]
    pub open: bool,
}

pub fn run(a: &ViewArgs) -> anyhow::Result<()> {
    let t0 = std::time::Instant::now();
    if !a.run.is_dir() {
        anyhow::bail!("{}: not a run folder (not a directory)", a.run.display());
    }
    // Held while the server runs: a rerun into R waits until the viewer is stopped.
    let _lock = super::query::lock_run(&a.run)?;
    let scene = super::query::scene_of(&a.run, a.scene.as_deref())?;
    let viewer = crate::view::Viewer::open(&a.run, &scene, a.mode, a.max_splats)
        .with_context(|| format!("opening run {} for viewing", a.run.display()))?;
    let listener = crate::view::bind(a.port)?;
    let addr = listener.local_addr()?;
    let url = format!("http://{addr}/");
    println!(
        "gs4city view: {} Gaussians of {} at {url} (127.0.0.1 only; Ctrl-C stops)  [{:.2} s]",
        viewer.len(),
        a.run.display(),
        t0.elapsed().as_secs_f64()
    );
    std::io::stdout().flush()?;
    if a.open
        && let Err(e) = std::process::Command::new("xdg-open")
            .arg(&url)
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .spawn()
    {
        eprintln!("warning: --open: cannot start xdg-open ({e}); open {url} by hand");
    }
    crate::view::serve(viewer, listener)?;
    Ok(())
}
