//! `gs4city view`: serve a finished run (`--run R`), or a scene before any run (`--scene S`), to
//! the browser on 127.0.0.1 (docs/view.md).
use std::io::Write;
use std::path::PathBuf;

use anyhow::Context;
use clap::Args;

use crate::layout::Mode;

#[derive(Debug, Args)]
pub struct ViewArgs {
    /// A run folder (`gs4city run --scene S --out R`): colours by class and building, queries,
    /// click → building → surface → part and the clicked point's coordinates.
    #[arg(long, value_name = "R", required_unless_present = "scene")]
    pub run: Option<PathBuf>,
    /// The scene folder: alone, the scene before any run (its Gaussians in RGB; a click gives
    /// the point's scene coordinates, for ground-control points); with --run, the scene the
    /// run was made from (default: the one recorded in R/run.json).
    #[arg(long, value_name = "S")]
    pub scene: Option<PathBuf>,
    /// With --run: which per-Gaussian labels, vote (R/lift) or learned (R/train); default:
    /// learned when R/train/gaussians.npy exists (as `gs4city query`).
    #[arg(long, requires = "run")]
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
    let mut lock = None;
    let (viewer, what) = match &a.run {
        Some(run) => {
            super::query::check_finished(run, a.scene.as_deref(), a.mode, false)?;
            // Held while the server runs: a run into R is refused until the viewer stops.
            lock = super::query::lock_run(run)?;
            let scene = super::query::scene_of(run, a.scene.as_deref())?;
            let v = crate::view::Viewer::open(
                run,
                &scene,
                a.mode,
                a.max_splats,
                super::query::run_crs(run),
            )
            .with_context(|| format!("opening run {} for viewing", run.display()))?;
            (v, format!("run {}", run.display()))
        }
        None => {
            let scene = a.scene.as_ref().expect("clap: --run or --scene");
            let crs = crate::scene::Scene::open(scene)
                .ok()
                .and_then(|s| srs_name_of(&s.gml));
            let v = crate::view::Viewer::open_scene(scene, crs)
                .with_context(|| format!("opening scene {} for viewing", scene.display()))?;
            (
                v,
                format!(
                    "scene {} (RGB; a click gives the point's coordinates)",
                    scene.display()
                ),
            )
        }
    };
    let listener = crate::view::bind(a.port)?;
    let addr = listener.local_addr()?;
    let url = format!("http://{addr}/");
    println!(
        "gs4city view: {} Gaussians of {what} at {url} (127.0.0.1 only; Ctrl-C stops)  [{:.2} s]",
        viewer.len(),
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
    drop(lock);
    Ok(())
}

/// The one `srsName` the head (64 KiB) of every CityGML file names, where they agree: the CRS
/// of a scene's clicked points before a run has parsed the model (the run's is
/// `R/citymodel/summary.json`'s).
fn srs_name_of(files: &[std::path::PathBuf]) -> Option<String> {
    use std::io::Read;
    let mut names = std::collections::BTreeSet::new();
    for f in files {
        let mut head = Vec::new();
        std::fs::File::open(f)
            .ok()?
            .take(64 << 10)
            .read_to_end(&mut head)
            .ok()?;
        let text = String::from_utf8_lossy(&head);
        let at = text.find("srsName=\"")? + "srsName=\"".len();
        let end = text[at..].find('"')?;
        names.insert(text[at..at + end].to_string());
    }
    (names.len() == 1).then(|| names.into_iter().next().expect("one name"))
}
