//! `gs4city export`: a finished run (or a selection of it) in the formats city tools read —
//! today a georeferenced 3D Tiles 1.1 tileset of `KHR_gaussian_splatting` glTF tiles with
//! per-splat building / surface / part feature ids and property tables (docs/export.md).
use std::collections::BTreeSet;
use std::path::PathBuf;

use anyhow::{Context, bail};
use clap::{Args, ValueEnum};

use crate::citymodel::CitymodelSummary;
use crate::layout::{Stage, Summary};
use crate::query::ColorBy;
use crate::tiles3d::{self, TilesOptions};

/// The export formats.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum Format {
    /// 3D Tiles 1.1 (tileset.json + tiles/*.glb).
    #[value(name = "3dtiles")]
    Tiles3d,
}

#[derive(Debug, Args)]
pub struct ExportArgs {
    #[command(flatten)]
    pub run: super::groups::RunRef,
    /// The output format.
    #[arg(long, value_enum, default_value = "3dtiles")]
    pub format: Format,
    /// Export only the Gaussians this selection holds (the query language of `gs4city query
    /// --where`, docs/query.md); default: every Gaussian.
    #[arg(long = "where", value_name = "EXPR")]
    pub where_: Option<String>,
    /// The city model's CRS (an EPSG code or any name PROJ knows); default: the srsName of the
    /// run's CityGML (R/citymodel/summary.json).
    #[arg(long, value_name = "EPSG:…")]
    pub crs: Option<String>,
    /// Splat colours: rgb (the input's), class (the class palette) or building (one colour per
    /// building).
    #[arg(long, value_name = "rgb|class|building", default_value = "rgb")]
    pub color_by: ColorBy,
    /// The largest number of splats in one tile: a quadtree node with more Gaussians is split,
    /// and every inner node holds at most this many coarse splats (the root too).
    #[arg(long, default_value_t = tiles3d::MAX_SPLATS)]
    pub max_splats: usize,
    /// Store each tile's splats SPZ-compressed (`KHR_gaussian_splatting_compression_spz_2`, a
    /// draft; lossy: docs/export.md), which CesiumJS draws as Gaussian splats.
    #[arg(long)]
    pub spz: bool,
    /// Output folder (built beside it, renamed when complete; an earlier export there is replaced).
    #[arg(long, value_name = "T")]
    pub out: PathBuf,
}

/// The CRS of the run: `--crs`, else the one srsName of its city model files (as
/// R/citymodel/summary.json records them; a merged tile plan has none, and its scene's files
/// are read).
fn run_crs(a: &ExportArgs, scene: &crate::scene::Scene) -> anyhow::Result<String> {
    if let Some(c) = &a.crs {
        return Ok(c.clone());
    }
    let dir = Stage::Citymodel.path(&a.run.run);
    let names: BTreeSet<String> = if dir.join("summary.json").is_file() {
        let s = CitymodelSummary::read(&dir)
            .with_context(|| format!("reading the city model's CRS from {}", dir.display()))?;
        s.files.into_iter().filter_map(|f| f.srs_name).collect()
    } else {
        let mut names = BTreeSet::new();
        for f in &scene.gml {
            let m = crate::cityjson::read_any(f)
                .with_context(|| format!("reading the city model's CRS from {}", f.display()))?;
            names.extend(m.srs_name);
        }
        names
    };
    match names.len() {
        1 => Ok(names.into_iter().next().expect("one name")),
        0 => bail!(
            "{}: no city model file names a CRS (no srsName on an Envelope or a geometry; CityJSON: no metadata.referenceSystem): give the CRS with --crs, e.g. --crs EPSG:25832",
            dir.join("summary.json").display()
        ),
        _ => bail!(
            "{}: the city model files name different CRSs ({}): give the one the coordinates are in with --crs",
            dir.join("summary.json").display(),
            names.into_iter().collect::<Vec<_>>().join(", ")
        ),
    }
}

pub fn run(a: &ExportArgs) -> anyhow::Result<()> {
    let Format::Tiles3d = a.format;
    if a.max_splats == 0 {
        bail!("--max-splats must be at least 1, got 0");
    }
    let _lock = super::query::lock_run(&a.run.run)?;
    super::query::check_finished(&a.run.run, a.run.scene.as_deref(), a.run.mode, false)?;
    let sr = super::query::open_run(&a.run, false)?;
    let crs = run_crs(a, &sr.scene)?;
    let georef = crate::crs::Georef::new(&crs)?;
    // The run's alignment; a merged tile plan's is its scene's.
    let apath = Stage::Citymodel.path(&a.run.run).join("alignment.json");
    let apath = match (&sr.scene.alignment, apath.is_file()) {
        (Some(scene_alignment), false) => scene_alignment.clone(),
        _ => apath,
    };
    let alignment = crate::alignment::Alignment::read(&apath)?;
    let (selected, query) = match &a.where_ {
        Some(w) => {
            let expr = super::query::parse("--where", w)?;
            let sel = sr.select_as("--where", w, &expr, Default::default())?;
            for w in &sel.warnings {
                eprintln!("warning: {w}");
            }
            (sr.gaussian_selection(&sel.labels), expr.to_string())
        }
        None => (vec![true; sr.label_of.len()], "every Gaussian".to_string()),
    };
    let opts = TilesOptions {
        max_splats: a.max_splats,
        spz: a.spz,
    };
    let s = crate::query::tiles(
        &sr, &selected, &query, a.color_by, &alignment, &georef, &opts, &a.out,
    )?;
    println!(
        "export 3dtiles `{}`: {} Gaussians in {} tiles ({} leaves, depth {}; {} coarse splats, {} in the root), {:.1} MB, CRS {} → root at lon {:.7}° lat {:.7}° h {:.2} m → {}  [{:.2} s]",
        s.query,
        s.splats,
        s.tiles,
        s.leaves,
        s.depth,
        s.coarse_splats,
        s.root_splats,
        s.bytes as f64 / 1e6,
        s.crs,
        s.root.lon,
        s.root.lat,
        s.root.height,
        a.out.display(),
        s.timing.total_s
    );
    if s.invalid > 0 {
        eprintln!(
            "warning: {} selected Gaussians have invalid values and were left out",
            s.invalid
        );
    }
    Ok(())
}
