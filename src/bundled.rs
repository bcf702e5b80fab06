//! The data bundled into the binary (so an installed `gs4city` runs `demo` and `synth --preset
//! small` without the source checkout): two real LoD3 CityGML buildings from Ingolstadt with their
//! textures (`data/citygml/`, CC BY-SA 4.0, see `data/README.md`). They are embedded at compile
//! time and written once, on first use, to a per-user cache folder named after their content
//! digest (`$XDG_CACHE_HOME/gs4city/` or `~/.cache/gs4city/`, else the system temporary folder).
use std::path::{Path, PathBuf};

/// `(path relative to the bundle folder, content)`.
const FILES: [(&str, &[u8]); 7] = [
    (
        "ingolstadt_4018106.gml",
        include_bytes!("../data/citygml/ingolstadt_4018106.gml"),
    ),
    (
        "ingolstadt_4018133.gml",
        include_bytes!("../data/citygml/ingolstadt_4018133.gml"),
    ),
    (
        "textures/Roofing_Shingles_Asphalt.jpg",
        include_bytes!("../data/citygml/textures/Roofing_Shingles_Asphalt.jpg"),
    ),
    (
        "textures/Roofing_Tile_Spanish.jpg",
        include_bytes!("../data/citygml/textures/Roofing_Tile_Spanish.jpg"),
    ),
    (
        "textures/Wood 02.jpg",
        include_bytes!("../data/citygml/textures/Wood 02.jpg"),
    ),
    (
        "textures/Wood_Cherry_Original.jpg",
        include_bytes!("../data/citygml/textures/Wood_Cherry_Original.jpg"),
    ),
    (
        "LICENSE-CC-BY-SA-4.0",
        include_bytes!("../data/citygml/LICENSE-CC-BY-SA-4.0"),
    ),
];

/// Errors of unpacking the bundle.
#[derive(Debug, thiserror::Error)]
#[error("cannot unpack the bundled CityGML into {path}: {err}")]
pub struct BundleError {
    pub path: PathBuf,
    pub err: std::io::Error,
}

fn cache_root() -> PathBuf {
    let from_env = |k: &str| {
        std::env::var_os(k)
            .filter(|v| !v.is_empty())
            .map(PathBuf::from)
    };
    from_env("XDG_CACHE_HOME")
        .or_else(|| from_env("HOME").map(|h| h.join(".cache")))
        .unwrap_or_else(std::env::temp_dir)
        .join("gs4city")
}

fn digest() -> String {
    let mut h = xxhash_rust::xxh3::Xxh3::new();
    for (name, bytes) in FILES {
        h.update(name.as_bytes());
        h.update(&(bytes.len() as u64).to_le_bytes());
        h.update(bytes);
    }
    format!("{:016x}", h.digest())
}

/// The folder holding the bundled CityGML files (and `textures/`), unpacked if needed.
pub fn citygml_dir() -> Result<PathBuf, BundleError> {
    let dir = cache_root()
        .join(format!("bundle-{}", digest()))
        .join("citygml");
    if FILES
        .iter()
        .all(|(n, b)| std::fs::metadata(dir.join(n)).is_ok_and(|m| m.len() == b.len() as u64))
    {
        return Ok(dir);
    }
    unpack(&dir)?;
    Ok(dir)
}

fn unpack(dir: &Path) -> Result<(), BundleError> {
    let err = |path: &Path| {
        let path = path.to_path_buf();
        move |err| BundleError { path, err }
    };
    for (name, bytes) in FILES {
        let path = dir.join(name);
        let parent = path.parent().unwrap_or(dir);
        std::fs::create_dir_all(parent).map_err(err(parent))?;
        // Temporary name + rename: a concurrent or interrupted unpack never leaves a short file.
        let tmp = parent.join(format!(
            ".{}.{}",
            std::process::id(),
            name.replace('/', "_")
        ));
        std::fs::write(&tmp, bytes).map_err(err(&tmp))?;
        std::fs::rename(&tmp, &path).map_err(err(&path))?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn unpacks_byte_identical_copies_of_data_citygml() {
        let dir = citygml_dir().unwrap();
        let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("data/citygml");
        for (name, _) in FILES {
            assert_eq!(
                std::fs::read(dir.join(name)).unwrap(),
                std::fs::read(src.join(name)).unwrap(),
                "{name}"
            );
        }
        // Every CityGML file and texture of data/citygml is bundled.
        let mut on_disk: Vec<String> = std::fs::read_dir(&src)
            .unwrap()
            .chain(std::fs::read_dir(src.join("textures")).unwrap())
            .filter_map(|e| e.ok())
            .filter(|e| e.path().is_file())
            .map(|e| {
                e.path()
                    .strip_prefix(&src)
                    .unwrap()
                    .to_string_lossy()
                    .into_owned()
            })
            .collect();
        on_disk.sort();
        let mut bundled: Vec<String> = FILES.iter().map(|(n, _)| n.to_string()).collect();
        bundled.sort();
        assert_eq!(on_disk, bundled);
    }
}
