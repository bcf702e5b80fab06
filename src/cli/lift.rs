//! `gs4city lift`: the closed-form weighted vote of per-view labels into the Gaussians, through
//! the contributions cache.
use std::path::PathBuf;

use anyhow::{Context, bail};
use clap::Args;

use super::groups::{ConfigArg, PriorTuning, SplitArgs, VoteTuning, merged};
use crate::cache::Cache;
use crate::idmap::LabelMaps;
use crate::labels::LabelTable;
use crate::lift;
use crate::scene::Split;
use crate::semantics;
use crate::{classes, colmap};

#[derive(Debug, Args)]
pub struct LiftArgs {
    #[command(flatten, next_help_heading = "Inputs")]
    src: LabelSourceArgs,
    #[command(flatten)]
    split: SplitArgs,
    #[command(flatten)]
    config: ConfigArg,
    #[command(flatten, next_help_heading = "Vote (config [vote])")]
    vote: VoteTuning,
    #[command(flatten, next_help_heading = "City-model prior (config [prior])")]
    prior: PriorTuning,
    /// Output folder.
    #[arg(long, help_heading = "Outputs")]
    out: PathBuf,
}

/// The inputs `lift` and `train` share: the scene's Gaussians and cameras, the cache, the
/// hierarchy table and the per-view labels.
#[derive(Debug, Args)]
pub(super) struct LabelSourceArgs {
    /// Pre-trained 3DGS scene (INRIA PLY) the cache was built from.
    #[arg(long)]
    pub(super) ply: PathBuf,
    /// COLMAP sparse model folder.
    #[arg(long)]
    pub(super) colmap: PathBuf,
    /// Contributions cache (`gs4city render --cache`, or a run's `render/`).
    #[arg(long)]
    pub(super) cache: PathBuf,
    /// Output folder of `gs4city citymodel` (semantics.json, alignment.json; mesh.ply for
    /// lift's city-model prior).
    #[arg(long)]
    pub(super) citymodel: PathBuf,
    /// The city-model labels `M_city` of this `gs4city raycast` output …
    #[arg(long, conflicts_with = "fuse", required_unless_present = "fuse")]
    pub(super) raycast: Option<PathBuf>,
    /// … or the fused labels of this `gs4city fuse` output (labels.json, <stem>.ids.npy).
    #[arg(long)]
    pub(super) fuse: Option<PathBuf>,
    /// The `gs4city raycast` output whose depth maps gate the city votes (default: --raycast).
    #[arg(long)]
    pub(super) depth: Option<PathBuf>,
}

/// What [`LabelSourceArgs`] name, read and checked.
pub(super) struct Loaded {
    pub(super) split: Split,
    pub(super) cache: Cache,
    pub(super) entities: Vec<semantics::Entity>,
    pub(super) maps: LabelMaps,
    pub(super) labels: LabelTable,
    /// The raycast folder of the depth gate and the alignment scale (citymodel/alignment.json).
    pub(super) depth: Option<(PathBuf, f64)>,
    /// The city model's mesh (`--citymodel`'s mesh.ply: the vote's city-model prior) and the
    /// alignment scale.
    pub(super) mesh: (PathBuf, f64),
}

impl LabelSourceArgs {
    /// Reads the views (split by `split`), the cache, the hierarchy table and the label source.
    pub(super) fn load(&self, split: &SplitArgs) -> anyhow::Result<Loaded> {
        let split = split.split(colmap::read_model(&self.colmap)?)?;
        let cache = Cache::open(&self.cache)
            .with_context(|| format!("opening the contributions cache {}", self.cache.display()))?;
        // The views the cache holds, at its resolution (a run's lower work resolution and
        // its choice of training views).
        let test = cache.views_as_cached(&split.test)?;
        if let Some(v) = split
            .test
            .iter()
            .find(|v| !test.iter().any(|t| t.name == v.name))
        {
            bail!(
                "{}: the cache has no test view {} (render it with the training views)",
                self.cache.display(),
                v.name
            );
        }
        let split = Split {
            train: cache.views_as_cached(&split.train)?,
            test,
        };
        let entities = semantics::read(&self.citymodel.join("semantics.json"))?;
        let (maps, labels) = label_source(self.raycast.as_ref(), self.fuse.as_ref(), &entities)?;
        // Scene units per metre (the depth gate's tolerance and the prior's reach); a model
        // folder without an alignment is in metres.
        let a = self.citymodel.join("alignment.json");
        let scale = if a.is_file() {
            crate::alignment::Alignment::read(&a)?.scale
        } else {
            1.0
        };
        let depth = self
            .depth
            .as_ref()
            .or(self.raycast.as_ref())
            .map(|d| (d.clone(), scale));
        Ok(Loaded {
            depth,
            mesh: (self.citymodel.join("mesh.ply"), scale),
            split,
            cache,
            entities,
            maps,
            labels,
        })
    }
}

impl Loaded {
    /// The inputs of the vote and of the training.
    pub(super) fn inputs<'a>(&'a self, ply: &'a std::path::Path) -> lift::LiftInputs<'a> {
        lift::LiftInputs {
            ply,
            cache: &self.cache,
            train: &self.split.train,
            test: &self.split.test,
            maps: &self.maps,
            labels: &self.labels,
            entities: &self.entities,
            city_depth: self.depth.as_ref().map(|(d, s)| (d.as_path(), *s)),
            city_mesh: Some((self.mesh.0.as_path(), self.mesh.1)),
        }
    }
}

pub fn run(args: &LiftArgs) -> anyhow::Result<()> {
    let cfg = args.config.load()?;
    let opts = super::groups::vote_options(
        &merged(&cfg.vote, &args.vote),
        &merged(&cfg.prior, &args.prior),
    )?;
    let l = args.src.load(&args.split)?;
    let s = lift::run(&l.inputs(&args.src.ply), &opts, &args.out)?;
    println!(
        "lifted labels into {} Gaussians ({} assigned) from {} training views: vote {:.2} s (load {:.2} s, accumulate {:.2} s, assign {:.3} s); {} test-view maps → {}",
        s.gaussians,
        s.assigned,
        s.train_views.len(),
        s.timing.vote_s,
        s.stats.load_s,
        s.stats.accumulate_s,
        s.stats.assign_s,
        s.test_views.len(),
        args.out.display()
    );
    Ok(())
}

/// The label maps and label table of `--raycast DIR` (`M_city`, the city-only table) or
/// `--fuse DIR` (fused maps, `labels.json`).
pub(super) fn label_source(
    raycast: Option<&PathBuf>,
    fuse: Option<&PathBuf>,
    entities: &[semantics::Entity],
) -> anyhow::Result<(LabelMaps, LabelTable)> {
    Ok(match (raycast, fuse) {
        (Some(r), _) => (
            LabelMaps::City(r.clone()),
            LabelTable::city(entities, &classes::table(entities))?,
        ),
        (None, Some(f)) => (
            LabelMaps::Fused(f.clone()),
            LabelTable::read(&f.join("labels.json"))?,
        ),
        (None, None) => bail!("give --raycast or --fuse"),
    })
}
