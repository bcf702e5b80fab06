//! `[city]`: a city of copies of the input CityGML blocks laid side by side on a grid.
//!
//! Copy `k` (column `k % nx`, row `k / nx`) is every input file with its coordinates shifted in
//! the ground plane by `(col·step_x, row·step_y)` — `step` = the block's footprint extent plus
//! `spacing`, rounded up to whole metres so that shifted coordinates stay exact in f64 — and
//! every `gml:id` and every reference to one (`="#id"` attributes such as `xlink:href`, `uri`,
//! `ring`; `<app:target>#id</app:target>`) suffixed `_r<k>`: the ids stay unique in the city and
//! an id of copy `k` names its copy. The copies are written as CityGML text (everything else
//! byte for byte) into a staging folder and read like any input; textures are looked up beside
//! the source files. The rest of `synth` then builds one world from all copies: the ground, the
//! objects and the cameras (their counts multiplied by the copies) over the whole city, and every
//! image rendered from all of its Gaussians, so neighbouring copies appear in each other's views.
use std::path::{Path, PathBuf};
use std::sync::LazyLock;

use glam::DVec3;
use regex::{Captures, Regex};

use super::SynthError;
use super::config::{CityBlocks, SynthConfig};

/// One written copy of one input file.
#[derive(Debug, Clone, PartialEq)]
pub struct Replica {
    /// The copy written (in the staging folder).
    pub path: PathBuf,
    /// The input file it copies.
    pub source: PathBuf,
    /// The folder the source's texture URIs are relative to.
    pub texture_dir: PathBuf,
    /// Copy index (ids suffixed `_r<copy>`).
    pub copy: usize,
}

/// The grid: per copy its ground-plane offset (metres, the CityGML CRS's x and y).
pub fn offsets(city: &CityBlocks, lo: DVec3, hi: DVec3) -> Vec<[f64; 2]> {
    let [nx, ny] = city.blocks;
    let step = [
        (hi.x - lo.x + city.spacing).max(0.0).ceil(),
        (hi.y - lo.y + city.spacing).max(0.0).ceil(),
    ];
    (0..nx * ny)
        .map(|k| [(k % nx) as f64 * step[0], (k / nx) as f64 * step[1]])
        .collect()
}

/// The configuration per copy scaled to the whole city: object and view counts × copies.
pub fn whole_city(cfg: &SynthConfig) -> SynthConfig {
    let n = cfg.city.copies();
    let mut c = cfg.clone();
    c.objects.trees *= n;
    c.objects.cars *= n;
    c.objects.persons *= n;
    c.cameras.orbit_views *= n;
    c.cameras.street_views *= n;
    c
}

/// Footprint box (x, y, z min and max) of the used polygons of the files.
fn extent(files: &[PathBuf]) -> Result<(DVec3, DVec3), SynthError> {
    let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
    for f in files {
        let m = crate::cityjson::read_any(f)?;
        for p in m.used_polygons() {
            for q in p.exterior.points.iter().filter(|q| q.is_finite()) {
                lo = lo.min(*q);
                hi = hi.max(*q);
            }
        }
    }
    if !lo.is_finite() || !hi.is_finite() {
        return Err(SynthError::Input(
            "[city] blocks: the CityGML input has no polygon with finite coordinates".into(),
        ));
    }
    Ok((lo, hi))
}

/// Writes copy `k` of every file for every offset into `dir` (`<k>_<i>/<file name>`), in the
/// order copy 0's files, copy 1's, …; returns them.
pub fn replicate(
    files: &[PathBuf],
    city: &CityBlocks,
    dir: &Path,
) -> Result<Vec<Replica>, SynthError> {
    for f in files {
        if crate::cityjson::is_cityjson_name(f) {
            return Err(SynthError::Input(format!(
                "{}: [city] blocks copies CityGML files only, not CityJSON",
                f.display()
            )));
        }
    }
    let (lo, hi) = extent(files)?;
    let offsets = offsets(city, lo, hi);
    let texts = files
        .iter()
        .map(|f| {
            std::fs::read_to_string(f).map_err(|e| {
                SynthError::Input(format!("{}: [city] blocks: cannot read: {e}", f.display()))
            })
        })
        .collect::<Result<Vec<_>, _>>()?;
    let mut out = Vec::new();
    for (k, off) in offsets.iter().enumerate() {
        for (i, (f, text)) in files.iter().zip(&texts).enumerate() {
            let shifted = shift_text(text, *off, k).map_err(|(line, why)| {
                SynthError::Input(format!("{}:{line}: [city] blocks: {why}", f.display()))
            })?;
            let sub = dir.join(format!("{k}_{i}"));
            crate::fsutil::create_dir(&sub)?;
            let name = f
                .file_name()
                .map(|n| format!("r{k}_{}", n.to_string_lossy()))
                .unwrap_or_else(|| format!("r{k}_{i}.gml"));
            let path = sub.join(name);
            std::fs::write(&path, shifted)
                .map_err(|e| SynthError::Input(format!("{}: cannot write: {e}", path.display())))?;
            out.push(Replica {
                path,
                source: f.clone(),
                texture_dir: f.parent().unwrap_or(Path::new(".")).to_path_buf(),
                copy: k,
            });
        }
    }
    Ok(out)
}

static COORDS: LazyLock<Regex> = LazyLock::new(|| {
    Regex::new(r"(<gml:(?:posList|pos|lowerCorner|upperCorner)\b([^>]*)>)([^<]*)(<)")
        .expect("regex")
});
static GML_ID: LazyLock<Regex> =
    LazyLock::new(|| Regex::new(r#"(\bgml:id=")([^"]*)(")"#).expect("regex"));
static HASH_REF: LazyLock<Regex> =
    LazyLock::new(|| Regex::new(r##"(="#)([^"]*)(")"##).expect("regex"));
static TARGET: LazyLock<Regex> = LazyLock::new(|| {
    Regex::new(r"(<app:target\b[^>]*>\s*#)([^<\s]*)(\s*</app:target>)").expect("regex")
});
static SRS_DIM: LazyLock<Regex> =
    LazyLock::new(|| Regex::new(r#"srsDimension="\s*([0-9]+)\s*""#).expect("regex"));

/// Copy `k` of a CityGML text: coordinates of `gml:pos`, `posList`, `lowerCorner` and
/// `upperCorner` shifted by `off` (x, y; 3-D coordinates only), ids and `#id` references
/// suffixed `_r<k>`. An error gives the 1-based line and why.
pub fn shift_text(text: &str, off: [f64; 2], k: usize) -> Result<String, (usize, String)> {
    let line_of = |pos: usize| text[..pos].bytes().filter(|&b| b == b'\n').count() + 1;
    let mut err: Option<(usize, String)> = None;
    let shifted = COORDS.replace_all(text, |c: &Captures| {
        let whole = c.get(0).expect("match");
        if let Some(d) = SRS_DIM.captures(&c[2]) {
            if &d[1] != "3" && err.is_none() {
                err = Some((
                    line_of(whole.start()),
                    format!("srsDimension {} (only 3-D coordinates are copied)", &d[1]),
                ));
            }
        }
        let vals: Result<Vec<f64>, _> = c[3].split_whitespace().map(str::parse::<f64>).collect();
        let vals = match vals {
            Ok(v) if v.len() % 3 == 0 => v,
            Ok(v) => {
                err.get_or_insert((
                    line_of(whole.start()),
                    format!("{} numbers, not x y z triples", v.len()),
                ));
                return whole.as_str().to_string();
            }
            Err(e) => {
                err.get_or_insert((line_of(whole.start()), format!("a coordinate: {e}")));
                return whole.as_str().to_string();
            }
        };
        let mut s = String::with_capacity(c[3].len() + 16);
        for (j, v) in vals.iter().enumerate() {
            if j > 0 {
                s.push(' ');
            }
            let v = match j % 3 {
                0 => v + off[0],
                1 => v + off[1],
                _ => *v,
            };
            s.push_str(&v.to_string());
        }
        format!("{}{s}{}", &c[1], &c[4])
    });
    if let Some(e) = err {
        return Err(e);
    }
    let suffix = |c: &Captures| format!("{}{}_r{k}{}", &c[1], &c[2], &c[3]);
    let s = GML_ID.replace_all(&shifted, suffix);
    let s = HASH_REF.replace_all(&s, suffix);
    let s = TARGET.replace_all(&s, suffix);
    Ok(s.into_owned())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shifts_coordinates_and_suffixes_ids_and_references() {
        let t = "<a gml:id=\"B1\">\n<gml:posList srsDimension=\"3\">1.5 2 3 4 5 6</gml:posList>\
                 <x xlink:href=\"#P1\"/><app:target>#R1</app:target><t ring=\"#R1\"/>\
                 <gml:lowerCorner>0 0 0</gml:lowerCorner></a>";
        let s = shift_text(t, [100.0, 200.0], 3).unwrap();
        assert_eq!(
            s,
            "<a gml:id=\"B1_r3\">\n<gml:posList srsDimension=\"3\">101.5 202 3 104 205 6</gml:posList>\
             <x xlink:href=\"#P1_r3\"/><app:target>#R1_r3</app:target><t ring=\"#R1_r3\"/>\
             <gml:lowerCorner>100 200 0</gml:lowerCorner></a>"
        );
    }

    #[test]
    fn refuses_2d_coordinates_and_broken_numbers_with_the_line() {
        let t = "<a>\n\n<gml:posList srsDimension=\"2\">1 2 3 4 5 6</gml:posList></a>";
        assert_eq!(shift_text(t, [1.0, 1.0], 0).unwrap_err().0, 3);
        let t = "<a>\n<gml:pos>1 2</gml:pos></a>";
        let e = shift_text(t, [1.0, 1.0], 0).unwrap_err();
        assert_eq!(e.0, 2);
        assert!(e.1.contains("2 numbers"), "{}", e.1);
        let t = "<gml:pos>1 x 2</gml:pos>";
        assert!(shift_text(t, [1.0, 1.0], 0).is_err());
    }

    #[test]
    fn grid_steps_by_extent_plus_spacing_rounded_up() {
        let c = CityBlocks {
            blocks: [3, 2],
            spacing: 20.0,
        };
        let o = offsets(&c, DVec3::new(10.0, 5.0, 0.0), DVec3::new(40.5, 15.0, 9.0));
        assert_eq!(o.len(), 6);
        assert_eq!(o[0], [0.0, 0.0]);
        assert_eq!(o[2], [102.0, 0.0]); // 2 · ceil(30.5 + 20)
        assert_eq!(o[4], [51.0, 30.0]); // column 1, row 1: ceil(10 + 20)
    }
}
