//! The `synth` configuration: TOML sections `[splats]`, `[ground]`, `[objects]`, `[cameras]`,
//! `[alignment]`, `[noise]`, `[output]`, every key optional with a default (docs/synth.md), and
//! the presets `small` and `street`. Unknown keys are errors naming the key and the file.
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::SynthError;

/// Splat placement on the true city model.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Splats {
    /// Gaussians per m² on building surfaces (area-weighted sampling).
    pub density: f64,
    /// In-plane standard deviation as a multiple of the sample spacing `1/√density`.
    pub scale_factor: f64,
    /// Standard deviation along the surface normal, metres.
    pub thickness: f64,
    /// Activated opacity of surface Gaussians.
    pub opacity: f64,
    /// How far windows and doors sit behind their wall plane, metres (the truth only).
    pub recess: f64,
    /// Colour building surfaces from their CityGML textures where the image exists.
    pub textures: bool,
    /// Strength of the view-dependent (SH degree 1) sky reflection of glass.
    pub glass_reflection: f64,
    /// Per-Gaussian colour jitter (standard deviation, 0..1 RGB units).
    pub color_jitter: f64,
}

impl Default for Splats {
    fn default() -> Self {
        Splats {
            density: 40.0,
            scale_factor: 0.7,
            thickness: 0.01,
            opacity: 0.95,
            recess: 0.15,
            textures: true,
            glass_reflection: 0.35,
            color_jitter: 0.03,
        }
    }
}

/// The ground plane around the buildings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Ground {
    /// Gaussians per m² on the ground.
    pub density: f64,
    /// Extent beyond the buildings' bounding box, metres.
    pub margin: f64,
    /// Pavement band along the façades, metres.
    pub pavement_width: f64,
    /// Road band beyond the pavement, metres (grass beyond that).
    pub road_width: f64,
    /// Radius of the water patch, metres (0 = none).
    pub water_radius: f64,
}

impl Default for Ground {
    fn default() -> Self {
        Ground {
            density: 8.0,
            margin: 15.0,
            pavement_width: 3.0,
            road_width: 8.0,
            water_radius: 5.0,
        }
    }
}

/// Objects the city model does not know.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Objects {
    pub trees: usize,
    pub cars: usize,
    pub persons: usize,
    /// Fraction of trees, cars and persons placed in front of a window or door (occluders).
    pub occluder_fraction: f64,
    /// Floaters as a fraction of all other Gaussians.
    pub floater_fraction: f64,
    /// Gaussians per tree crown.
    pub tree_gaussians: usize,
}

impl Default for Objects {
    fn default() -> Self {
        Objects {
            trees: 4,
            cars: 4,
            persons: 6,
            occluder_fraction: 0.5,
            floater_fraction: 0.001,
            tree_gaussians: 2500,
        }
    }
}

/// Cameras: oblique drone orbits and street-level views.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Cameras {
    pub width: u32,
    pub height: u32,
    /// Horizontal field of view, degrees.
    pub hfov_deg: f64,
    /// fy / fx (the DJI Mavic 3E sensor: 17.3 × 13.0 mm over 5280 × 3956 px).
    pub pixel_aspect: f64,
    pub orbit_views: usize,
    /// Horizontal distance from the target, metres `[min, max]`.
    pub orbit_radius: [f64; 2],
    /// Downward pitch, degrees `[min, max]`.
    pub orbit_pitch_deg: [f64; 2],
    pub street_views: usize,
    /// Camera height above the ground, metres.
    pub street_height: f64,
    /// Distance from the façade, metres `[min, max]`.
    pub street_distance: [f64; 2],
    /// Every n-th view (sorted by name) is a test view.
    pub test_every: usize,
    /// Background colour of the renders (sky), RGB 0..1.
    pub background: [f32; 3],
}

impl Default for Cameras {
    fn default() -> Self {
        Cameras {
            width: 660,
            height: 494,
            hfov_deg: 73.7,
            pixel_aspect: (17.3 / 5280.0) / (13.0 / 3956.0),
            orbit_views: 12,
            orbit_radius: [40.0, 60.0],
            orbit_pitch_deg: [30.0, 45.0],
            street_views: 4,
            street_height: 1.7,
            street_distance: [8.0, 14.0],
            test_every: 8,
            background: [0.62, 0.74, 0.88],
        }
    }
}

/// The true georeferenced → scene alignment (origin = floored bbox minimum).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrueAlignment {
    /// Rotation about the vertical axis, degrees.
    pub rotation_deg: f64,
    pub scale: f64,
    pub translation: [f64; 3],
}

impl Default for TrueAlignment {
    fn default() -> Self {
        TrueAlignment {
            rotation_deg: 0.0,
            scale: 1.0,
            translation: [0.0; 3],
        }
    }
}

/// Simulated error of the alignment handed to the pipeline.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Noise {
    /// Translation error, metres (a random direction of this length).
    pub translation_m: f64,
    /// Rotation error, degrees (about a random axis).
    pub rotation_deg: f64,
    /// Relative scale error (`scale · (1 + e)`, sign random).
    pub scale: f64,
}

/// Output options.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Output {
    /// Views shown in `contact_sheet.png`.
    pub contact_views: usize,
    /// Accumulated alpha below which a GT pixel is −1.
    pub min_alpha: f32,
}

impl Default for Output {
    fn default() -> Self {
        Output {
            contact_views: 4,
            min_alpha: 0.5,
        }
    }
}

/// The whole configuration.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SynthConfig {
    pub seed: u64,
    /// CityGML files or folders (searched for `*.gml`, sorted); relative to the config file.
    pub citygml: Vec<PathBuf>,
    pub splats: Splats,
    pub ground: Ground,
    pub objects: Objects,
    pub cameras: Cameras,
    pub alignment: TrueAlignment,
    pub noise: Noise,
    pub output: Output,
    /// SIMULATED SAM masks (docs/sam.md: every key of the noise model).
    pub masks: super::masks::MaskNoise,
    /// SIMULATED CLIP features (docs/sam.md).
    pub features: super::masks::FeatureNoise,
    /// The city model handed to the pipeline (docs/synth.md `[model]`).
    pub model: ModelEdit,
    /// A city of copies of the input blocks side by side (docs/synth.md `[city]`).
    pub city: CityBlocks,
}

/// A grid of copies of the input CityGML blocks (`[city]`): copy `k` at column `k % nx`, row
/// `k / nx`, shifted in the ground plane by the block's extent plus `spacing` per step, its ids
/// suffixed `_r<k>`; object and view counts are per copy.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CityBlocks {
    /// Copies along x and along y (`[1, 1]`: the block alone, nothing replicated).
    pub blocks: [usize; 2],
    /// Gap between neighbouring copies' footprint boxes, metres.
    pub spacing: f64,
}

impl Default for CityBlocks {
    fn default() -> Self {
        CityBlocks {
            blocks: [1, 1],
            spacing: 20.0,
        }
    }
}

impl CityBlocks {
    /// Number of copies.
    pub fn copies(&self) -> usize {
        self.blocks[0] * self.blocks[1]
    }
}

/// What the pipeline's city model lacks that the truth has.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ModelEdit {
    /// Share of windows and doors removed from the pipeline's model (0 none, 1 all: an LoD2
    /// model), drawn with the seed; the model is then written as CityJSON, the truth keeps them.
    pub drop_openings: f64,
}

/// A named preset.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Preset {
    /// Bundled data (`data/citygml/`): two Ingolstadt buildings, ~14 views.
    Small,
    /// The 27-building Ingolstadt street block ([`street_block`]).
    Street,
}

/// The 27-building Ingolstadt block of the street preset: `../shared/data/citygml/ingolstadt_north`
/// relative to the working directory, else `shared/data/citygml/ingolstadt_north` beside an
/// ancestor folder of the executable (a checkout's `target/release/gs4city` finds the `shared/`
/// beside the checkout). `None` when neither exists (then `--citygml` must name it).
pub fn street_block() -> Option<PathBuf> {
    let rel = Path::new("shared/data/citygml/ingolstadt_north");
    let cwd = Path::new("..").join(rel);
    if cwd.is_dir() {
        return Some(cwd);
    }
    let exe = std::env::current_exe().ok()?;
    exe.ancestors()
        .skip(1)
        .map(|a| a.join(rel))
        .find(|p| p.is_dir())
}

impl SynthConfig {
    /// A preset's configuration.
    pub fn preset(p: Preset) -> SynthConfig {
        let mut c = SynthConfig::default();
        match p {
            Preset::Small => {
                // The bundled buildings; an unpacking error surfaces as "no CityGML input".
                c.citygml = crate::bundled::citygml_dir().into_iter().collect();
                c.splats.density = 60.0;
                c.cameras.orbit_views = 10;
                c.cameras.street_views = 4;
                c.cameras.orbit_radius = [35.0, 50.0];
            }
            Preset::Street => {
                c.citygml = street_block().into_iter().collect();
                c.splats.density = 28.0;
                c.ground.density = 5.0;
                c.objects.trees = 24;
                c.objects.cars = 20;
                c.objects.persons = 30;
                c.cameras.orbit_views = 96;
                c.cameras.street_views = 32;
            }
        }
        c
    }

    /// Reads a TOML file over `base` (keys given replace the base's).
    pub fn load(path: &Path, base: SynthConfig) -> Result<SynthConfig, SynthError> {
        let text = std::fs::read_to_string(path).map_err(|e| SynthError::Config {
            path: path.to_path_buf(),
            why: e.to_string(),
        })?;
        let cfg_err = |why: String| SynthError::Config {
            path: path.to_path_buf(),
            why,
        };
        let over: toml::Table = text
            .parse()
            .map_err(|e: toml::de::Error| cfg_err(e.to_string()))?;
        let mut merged = toml::Table::try_from(&base).map_err(|e| cfg_err(e.to_string()))?;
        merge(&mut merged, over);
        let mut cfg: SynthConfig = merged
            .try_into()
            .map_err(|e: toml::de::Error| cfg_err(e.to_string()))?;
        let dir = path.parent().unwrap_or(Path::new("."));
        let given_files = text
            .parse::<toml::Table>()
            .map(|t| t.contains_key("citygml"))
            .unwrap_or(false);
        if given_files {
            cfg.citygml = cfg
                .citygml
                .iter()
                .map(|p| {
                    if p.is_absolute() {
                        p.clone()
                    } else {
                        dir.join(p)
                    }
                })
                .collect();
        }
        cfg.validate(path)?;
        Ok(cfg)
    }

    /// Checks value ranges; errors name the key and the source (`what`).
    pub fn validate(&self, source: &Path) -> Result<(), SynthError> {
        let bad = |key: &str, why: &str| {
            Err(SynthError::Config {
                path: source.to_path_buf(),
                why: format!("key `{key}`: {why}"),
            })
        };
        if !(0.0..=1.0).contains(&self.model.drop_openings) {
            return bad("model.drop_openings", "must be in [0, 1]");
        }
        let [nx, ny] = self.city.blocks;
        if !(1..=64).contains(&nx) || !(1..=64).contains(&ny) {
            return bad("city.blocks", "need 1..64 copies along x and along y");
        }
        if !(0.0..=10_000.0).contains(&self.city.spacing) {
            return bad("city.spacing", "must be in [0, 10000] m");
        }
        let copies = self.city.copies();
        let o = &self.objects;
        if copies * (self.cameras.orbit_views + self.cameras.street_views) > 100_000
            || copies * (o.trees + o.cars + o.persons) > 100_000
        {
            return bad(
                "city.blocks",
                "the copies × the views (or objects) per copy exceed 100000",
            );
        }
        let s = &self.splats;
        if !(s.density > 0.0 && s.density <= 10_000.0) {
            return bad("splats.density", "must be in (0, 10000] per m²");
        }
        if !(s.scale_factor > 0.0 && s.scale_factor <= 10.0) {
            return bad("splats.scale_factor", "must be in (0, 10]");
        }
        if !(s.thickness > 0.0 && s.thickness < 1.0) {
            return bad("splats.thickness", "must be in (0, 1) m");
        }
        if !(s.opacity > 0.0 && s.opacity < 1.0) {
            return bad("splats.opacity", "must be in (0, 1)");
        }
        if !(0.0..=2.0).contains(&s.recess) {
            return bad("splats.recess", "must be in [0, 2] m");
        }
        if !(0.0..=1.0).contains(&s.glass_reflection) {
            return bad("splats.glass_reflection", "must be in [0, 1]");
        }
        if !(0.0..=0.5).contains(&s.color_jitter) {
            return bad("splats.color_jitter", "must be in [0, 0.5]");
        }
        let g = &self.ground;
        if !(g.density >= 0.0 && g.density <= 1000.0) {
            return bad("ground.density", "must be in [0, 1000] per m²");
        }
        for (k, v) in [
            ("ground.margin", g.margin),
            ("ground.pavement_width", g.pavement_width),
            ("ground.road_width", g.road_width),
            ("ground.water_radius", g.water_radius),
        ] {
            if !(0.0..=1000.0).contains(&v) {
                return bad(k, "must be in [0, 1000] m");
            }
        }
        let o = &self.objects;
        if !(0.0..=1.0).contains(&o.occluder_fraction) {
            return bad("objects.occluder_fraction", "must be in [0, 1]");
        }
        if !(0.0..=0.5).contains(&o.floater_fraction) {
            return bad("objects.floater_fraction", "must be in [0, 0.5]");
        }
        if o.trees + o.cars + o.persons > 100_000 || o.tree_gaussians > 1_000_000 {
            return bad("objects", "too many objects");
        }
        let c = &self.cameras;
        if c.width < 16 || c.height < 16 || c.width > 8192 || c.height > 8192 {
            return bad("cameras.width/height", "must be in [16, 8192] px");
        }
        if !(c.hfov_deg > 5.0 && c.hfov_deg < 170.0) {
            return bad("cameras.hfov_deg", "must be in (5, 170)");
        }
        if !(c.pixel_aspect > 0.5 && c.pixel_aspect < 2.0) {
            return bad("cameras.pixel_aspect", "must be in (0.5, 2)");
        }
        if c.orbit_views + c.street_views == 0 || c.orbit_views + c.street_views > 100_000 {
            return bad("cameras.orbit_views", "need 1..100000 views in all");
        }
        if !(c.orbit_radius[0] > 0.0 && c.orbit_radius[0] <= c.orbit_radius[1]) {
            return bad("cameras.orbit_radius", "need 0 < min ≤ max");
        }
        if !(c.orbit_pitch_deg[0] >= 0.0
            && c.orbit_pitch_deg[0] <= c.orbit_pitch_deg[1]
            && c.orbit_pitch_deg[1] < 90.0)
        {
            return bad("cameras.orbit_pitch_deg", "need 0 ≤ min ≤ max < 90");
        }
        if !(c.street_distance[0] > 0.0 && c.street_distance[0] <= c.street_distance[1]) {
            return bad("cameras.street_distance", "need 0 < min ≤ max");
        }
        if !(c.street_height > 0.0 && c.street_height < 100.0) {
            return bad("cameras.street_height", "must be in (0, 100) m");
        }
        if c.test_every == 0 {
            return bad("cameras.test_every", "must be ≥ 1");
        }
        if c.background.iter().any(|v| !(0.0..=1.0).contains(v)) {
            return bad("cameras.background", "values must be in [0, 1]");
        }
        let a = &self.alignment;
        if !(a.scale > 0.0
            && a.scale.is_finite()
            && a.rotation_deg.is_finite()
            && a.translation.iter().all(|v| v.is_finite()))
        {
            return bad("alignment", "scale must be > 0 and all values finite");
        }
        let n = &self.noise;
        if !(n.translation_m >= 0.0 && n.translation_m.is_finite()) {
            return bad("noise.translation_m", "must be ≥ 0");
        }
        if !(0.0..=180.0).contains(&n.rotation_deg) {
            return bad("noise.rotation_deg", "must be in [0, 180]");
        }
        if !(0.0..0.9).contains(&n.scale) {
            return bad("noise.scale", "must be in [0, 0.9)");
        }
        if !(0.0..1.0).contains(&self.output.min_alpha) {
            return bad("output.min_alpha", "must be in [0, 1)");
        }
        Ok(())
    }
}

fn merge(base: &mut toml::Table, over: toml::Table) {
    for (k, v) in over {
        match (base.get_mut(&k), v) {
            (Some(toml::Value::Table(b)), toml::Value::Table(o)) => merge(b, o),
            (_, v) => {
                base.insert(k, v);
            }
        }
    }
}

/// The CityGML files named by `paths`: files as given, folders searched recursively for
/// `*.gml` / `*.xml` (sorted by path), each file once ([`crate::citymodel::collect_files`]:
/// symbolic-link loops end, repeated files are read once); its warnings go to the log.
pub fn collect_files(paths: &[PathBuf]) -> Result<Vec<PathBuf>, SynthError> {
    let found =
        crate::citymodel::collect_files(paths).map_err(|e| SynthError::Input(e.to_string()))?;
    for w in &found.warnings {
        log::warn!("{w}");
    }
    Ok(found.files)
}
