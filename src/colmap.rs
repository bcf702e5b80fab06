//! COLMAP sparse models (a reader: depends on no stage): `cameras`, `images` and
//! `points3D` in the binary (`.bin`) and text (`.txt`) formats, read into [`camera::View`]s
//! and written back (used to write synthetic scenes). Camera models: SIMPLE_PINHOLE,
//! PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV.
use std::path::{Path, PathBuf};

use crate::camera::{self, Camera, Distortion, Intrinsics, Pose, View};
use crate::fsutil::{self, FsError};

/// Errors of COLMAP model reading and writing. Every message names the file; text-format
/// errors also name the line, image errors the image.
#[derive(Debug, thiserror::Error)]
pub enum ColmapError {
    #[error("cannot read {path}: {err}")]
    Io { path: PathBuf, err: std::io::Error },
    #[error(
        "{dir}: no COLMAP model (expected cameras.bin + images.bin or cameras.txt + images.txt)"
    )]
    NoModel { dir: PathBuf },
    #[error("{path}: truncated while reading {what}")]
    Truncated { path: PathBuf, what: String },
    #[error("{path}:{line}: {why}")]
    Parse {
        path: PathBuf,
        line: usize,
        why: String,
    },
    #[error("{path}: camera {camera_id}: unknown or unsupported camera model {model}")]
    UnknownModel {
        path: PathBuf,
        camera_id: u32,
        model: String,
    },
    #[error("{path}: camera {camera_id}: {why}")]
    BadCamera {
        path: PathBuf,
        camera_id: u32,
        why: String,
    },
    #[error("{path}{}: image {image_id} ({name}): {why}", line.map(|l| format!(":{l}")).unwrap_or_default())]
    BadPose {
        path: PathBuf,
        /// The line in `images.txt` (none in `images.bin`).
        line: Option<usize>,
        image_id: u32,
        name: String,
        why: String,
    },
    #[error(
        "{path}: image {image_id} ({name}) refers to camera {camera_id}, which is not in cameras"
    )]
    MissingCamera {
        path: PathBuf,
        image_id: u32,
        name: String,
        camera_id: u32,
    },
    #[error("{path}: duplicate {what} id {id}")]
    Duplicate {
        path: PathBuf,
        what: &'static str,
        id: u64,
    },
    #[error("{path}: image name {name:?} is used by images {first} and {second}")]
    DuplicateName {
        path: PathBuf,
        name: String,
        first: u32,
        second: u32,
    },
    #[error(
        "{path}: image {image_id} ({name:?}): the name has no file stem (an image file name such as frame_0001.png is required)"
    )]
    NoStem {
        path: PathBuf,
        image_id: u32,
        name: String,
    },
    #[error("{path}: {extra} bytes after the last {what} (a damaged or concatenated file)")]
    Trailing {
        path: PathBuf,
        extra: usize,
        what: &'static str,
    },
    #[error(transparent)]
    Write(#[from] FsError),
}

/// A COLMAP camera model: id, name and parameter count.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Model {
    SimplePinhole,
    Pinhole,
    SimpleRadial,
    Radial,
    OpenCv,
    FullOpenCv,
}

impl Model {
    /// COLMAP's numeric model id.
    pub fn id(self) -> i32 {
        match self {
            Model::SimplePinhole => 0,
            Model::Pinhole => 1,
            Model::SimpleRadial => 2,
            Model::Radial => 3,
            Model::OpenCv => 4,
            Model::FullOpenCv => 6,
        }
    }
    /// COLMAP's model name.
    pub fn name(self) -> &'static str {
        match self {
            Model::SimplePinhole => "SIMPLE_PINHOLE",
            Model::Pinhole => "PINHOLE",
            Model::SimpleRadial => "SIMPLE_RADIAL",
            Model::Radial => "RADIAL",
            Model::OpenCv => "OPENCV",
            Model::FullOpenCv => "FULL_OPENCV",
        }
    }
    /// Number of parameters.
    pub fn num_params(self) -> usize {
        match self {
            Model::SimplePinhole => 3,
            Model::Pinhole => 4,
            Model::SimpleRadial => 4,
            Model::Radial => 5,
            Model::OpenCv => 8,
            Model::FullOpenCv => 12,
        }
    }
    const ALL: [Model; 6] = [
        Model::SimplePinhole,
        Model::Pinhole,
        Model::SimpleRadial,
        Model::Radial,
        Model::OpenCv,
        Model::FullOpenCv,
    ];
    /// The model with COLMAP id `id`.
    pub fn from_id(id: i32) -> Option<Model> {
        Model::ALL.into_iter().find(|m| m.id() == id)
    }
    /// The model named `name`.
    pub fn from_name(name: &str) -> Option<Model> {
        Model::ALL.into_iter().find(|m| m.name() == name)
    }

    /// Intrinsics from COLMAP parameters (length checked by the caller).
    fn intrinsics(self, width: u32, height: u32, p: &[f64]) -> Intrinsics {
        let (fx, fy, cx, cy, rest) = match self {
            Model::SimplePinhole | Model::SimpleRadial | Model::Radial => {
                (p[0], p[0], p[1], p[2], &p[3..])
            }
            Model::Pinhole | Model::OpenCv | Model::FullOpenCv => (p[0], p[1], p[2], p[3], &p[4..]),
        };
        let distortion = match self {
            Model::SimplePinhole | Model::Pinhole => Distortion::None,
            Model::SimpleRadial => Distortion::Radial {
                k1: rest[0],
                k2: 0.0,
            },
            Model::Radial => Distortion::Radial {
                k1: rest[0],
                k2: rest[1],
            },
            Model::OpenCv => Distortion::OpenCv {
                k1: rest[0],
                k2: rest[1],
                p1: rest[2],
                p2: rest[3],
            },
            Model::FullOpenCv => Distortion::FullOpenCv {
                k: [rest[0], rest[1], rest[4], rest[5], rest[6], rest[7]],
                p1: rest[2],
                p2: rest[3],
            },
        };
        Intrinsics {
            width,
            height,
            fx,
            fy,
            cx,
            cy,
            distortion,
        }
    }

    /// The simplest model representing `k` exactly, and its parameters.
    pub fn for_intrinsics(k: &Intrinsics) -> (Model, Vec<f64>) {
        let single_f = k.fx == k.fy;
        match k.distortion {
            Distortion::None if single_f => (Model::SimplePinhole, vec![k.fx, k.cx, k.cy]),
            Distortion::None => (Model::Pinhole, vec![k.fx, k.fy, k.cx, k.cy]),
            Distortion::Radial { k1, k2 } if single_f && k2 == 0.0 => {
                (Model::SimpleRadial, vec![k.fx, k.cx, k.cy, k1])
            }
            Distortion::Radial { k1, k2 } if single_f => {
                (Model::Radial, vec![k.fx, k.cx, k.cy, k1, k2])
            }
            Distortion::Radial { k1, k2 } => (
                Model::OpenCv,
                vec![k.fx, k.fy, k.cx, k.cy, k1, k2, 0.0, 0.0],
            ),
            Distortion::OpenCv { k1, k2, p1, p2 } => {
                (Model::OpenCv, vec![k.fx, k.fy, k.cx, k.cy, k1, k2, p1, p2])
            }
            Distortion::FullOpenCv { k: kk, p1, p2 } => (
                Model::FullOpenCv,
                vec![
                    k.fx, k.fy, k.cx, k.cy, kk[0], kk[1], p1, p2, kk[2], kk[3], kk[4], kk[5],
                ],
            ),
        }
    }
}

/// One COLMAP camera (shared intrinsics).
#[derive(Debug, Clone, PartialEq)]
pub struct ColmapCamera {
    pub camera_id: u32,
    pub model: Model,
    pub intrinsics: Intrinsics,
}

/// One COLMAP image before its camera is resolved.
#[derive(Debug, Clone, PartialEq)]
struct RawImage {
    image_id: u32,
    camera_id: u32,
    name: String,
    pose: Pose,
}

/// One sparse 3D point (its track is read and dropped).
#[derive(Debug, Clone, PartialEq)]
pub struct Point3D {
    pub id: u64,
    pub xyz: [f64; 3],
    pub rgb: [u8; 3],
    pub error: f64,
}

// ---------------------------------------------------------------- binary

struct BinReader<'a> {
    path: &'a Path,
    bytes: &'a [u8],
    pos: usize,
}

impl<'a> BinReader<'a> {
    fn take(&mut self, n: usize, what: &dyn Fn() -> String) -> Result<&'a [u8], ColmapError> {
        if self.bytes.len() - self.pos < n {
            return Err(ColmapError::Truncated {
                path: self.path.to_path_buf(),
                what: what(),
            });
        }
        let s = &self.bytes[self.pos..self.pos + n];
        self.pos += n;
        Ok(s)
    }
    fn u64(&mut self, what: &dyn Fn() -> String) -> Result<u64, ColmapError> {
        let b = self.take(8, what)?;
        Ok(u64::from_le_bytes(b.try_into().unwrap_or([0; 8])))
    }
    fn u32(&mut self, what: &dyn Fn() -> String) -> Result<u32, ColmapError> {
        let b = self.take(4, what)?;
        Ok(u32::from_le_bytes(b.try_into().unwrap_or([0; 4])))
    }
    fn i32(&mut self, what: &dyn Fn() -> String) -> Result<i32, ColmapError> {
        Ok(self.u32(what)? as i32)
    }
    fn f64(&mut self, what: &dyn Fn() -> String) -> Result<f64, ColmapError> {
        Ok(f64::from_bits(self.u64(what)?))
    }
    fn f64s<const N: usize>(&mut self, what: &dyn Fn() -> String) -> Result<[f64; N], ColmapError> {
        let mut out = [0.0; N];
        for v in &mut out {
            *v = self.f64(what)?;
        }
        Ok(out)
    }
    /// Ends the file: nothing may follow the last record.
    fn end(&self, what: &'static str) -> Result<(), ColmapError> {
        match self.bytes.len() - self.pos {
            0 => Ok(()),
            extra => Err(ColmapError::Trailing {
                path: self.path.to_path_buf(),
                extra,
                what,
            }),
        }
    }
    fn count(&mut self, elem: usize, what: &dyn Fn() -> String) -> Result<usize, ColmapError> {
        let n = self.u64(what)?;
        // A count that cannot fit in the rest of the file is a truncation, not an allocation.
        let left = (self.bytes.len() - self.pos) as u64;
        if n.saturating_mul(elem as u64) > left {
            return Err(ColmapError::Truncated {
                path: self.path.to_path_buf(),
                what: format!("{} (count {n} exceeds the file)", what()),
            });
        }
        Ok(n as usize)
    }
}

fn read_file(path: &Path) -> Result<Vec<u8>, ColmapError> {
    std::fs::read(path).map_err(|err| ColmapError::Io {
        path: path.to_path_buf(),
        err,
    })
}

fn parse_cameras_bin(path: &Path, bytes: &[u8]) -> Result<Vec<ColmapCamera>, ColmapError> {
    let mut r = BinReader {
        path,
        bytes,
        pos: 0,
    };
    let n = r.count(24, &|| "the number of cameras".into())?;
    let mut out = Vec::with_capacity(n);
    for i in 0..n {
        let what = move || format!("camera #{i}");
        let camera_id = r.u32(&what)?;
        let model_id = r.i32(&what)?;
        let width = r.u64(&what)?;
        let height = r.u64(&what)?;
        let model = Model::from_id(model_id).ok_or_else(|| ColmapError::UnknownModel {
            path: path.to_path_buf(),
            camera_id,
            model: format!("id {model_id}"),
        })?;
        let mut params = Vec::with_capacity(model.num_params());
        for _ in 0..model.num_params() {
            params.push(r.f64(&what)?);
        }
        let cam = make_camera(camera_id, model, width, height, &params).map_err(|why| {
            ColmapError::BadCamera {
                path: path.to_path_buf(),
                camera_id,
                why,
            }
        })?;
        out.push(cam);
    }
    r.end("camera")?;
    Ok(out)
}

/// A camera from its COLMAP fields, checked with [`Intrinsics::validate`]; the error is the
/// reason (the caller names the file, line and camera).
fn make_camera(
    camera_id: u32,
    model: Model,
    width: u64,
    height: u64,
    params: &[f64],
) -> Result<ColmapCamera, String> {
    if params.len() != model.num_params() {
        return Err(format!(
            "{} takes {} parameters, found {}",
            model.name(),
            model.num_params(),
            params.len()
        ));
    }
    let (Ok(width), Ok(height)) = (u32::try_from(width), u32::try_from(height)) else {
        return Err(format!("image size {width}×{height} is too large"));
    };
    let cam = ColmapCamera {
        camera_id,
        model,
        intrinsics: model.intrinsics(width, height, params),
    };
    cam.intrinsics.validate().map_err(|e| e.0)?;
    Ok(cam)
}

/// A pose from a COLMAP quaternion and translation, checked with [`Pose::validate`].
fn make_pose(q: [f64; 4], t: [f64; 3]) -> Result<Pose, String> {
    let pose = Pose::from_colmap(q, t).ok_or_else(|| {
        "invalid pose: the quaternion is zero or a value is not a finite number".to_string()
    })?;
    pose.validate().map_err(|e| e.0)?;
    Ok(pose)
}

fn parse_images_bin(path: &Path, bytes: &[u8]) -> Result<Vec<RawImage>, ColmapError> {
    let mut r = BinReader {
        path,
        bytes,
        pos: 0,
    };
    let n = r.count(64, &|| "the number of images".into())?;
    let mut out = Vec::with_capacity(n);
    for i in 0..n {
        let what = move || format!("image #{i}");
        let image_id = r.u32(&what)?;
        let q = r.f64s::<4>(&what)?;
        let t = r.f64s::<3>(&what)?;
        let camera_id = r.u32(&what)?;
        let start = r.pos;
        let Some(len) = bytes[start..].iter().position(|&b| b == 0) else {
            return Err(ColmapError::Truncated {
                path: path.to_path_buf(),
                what: format!("the name of image {image_id}"),
            });
        };
        let name = String::from_utf8_lossy(&bytes[start..start + len]).into_owned();
        r.pos = start + len + 1;
        let what = || format!("the 2D points of image {image_id} ({name})");
        let np = r.count(24, &what)?;
        r.take(np * 24, &what)?;
        let pose = make_pose(q, t).map_err(|why| ColmapError::BadPose {
            path: path.to_path_buf(),
            line: None,
            image_id,
            name: name.clone(),
            why,
        })?;
        out.push(RawImage {
            image_id,
            camera_id,
            name,
            pose,
        });
    }
    r.end("image")?;
    Ok(out)
}

fn parse_points_bin(path: &Path, bytes: &[u8]) -> Result<Vec<Point3D>, ColmapError> {
    let mut r = BinReader {
        path,
        bytes,
        pos: 0,
    };
    let n = r.count(43, &|| "the number of 3D points".into())?;
    let mut out = Vec::with_capacity(n);
    for i in 0..n {
        let what = move || format!("3D point #{i}");
        let id = r.u64(&what)?;
        let xyz = r.f64s::<3>(&what)?;
        let c = r.take(3, &what)?;
        let rgb = [c[0], c[1], c[2]];
        let error = r.f64(&what)?;
        let track = r.count(8, &what)?;
        r.take(track * 8, &what)?;
        out.push(Point3D {
            id,
            xyz,
            rgb,
            error,
        });
    }
    r.end("3D point")?;
    Ok(out)
}

// ---------------------------------------------------------------- text

/// Data lines of a text file with their 1-based line numbers (comments and blank lines skipped).
fn data_lines(text: &str) -> impl Iterator<Item = (usize, &str)> {
    text.lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l.trim()))
        .filter(|(_, l)| !l.is_empty() && !l.starts_with('#'))
}

fn parse_err(path: &Path, line: usize, why: impl Into<String>) -> ColmapError {
    ColmapError::Parse {
        path: path.to_path_buf(),
        line,
        why: why.into(),
    }
}

fn field<T: std::str::FromStr>(
    path: &Path,
    line: usize,
    tok: Option<&str>,
    what: &str,
) -> Result<T, ColmapError> {
    let tok = tok.ok_or_else(|| parse_err(path, line, format!("missing {what}")))?;
    tok.parse()
        .map_err(|_| parse_err(path, line, format!("bad {what} {tok:?}")))
}

fn parse_cameras_txt(path: &Path, text: &str) -> Result<Vec<ColmapCamera>, ColmapError> {
    let mut out = Vec::new();
    for (line, l) in data_lines(text) {
        let mut it = l.split_whitespace();
        let camera_id: u32 = field(path, line, it.next(), "CAMERA_ID")?;
        let model_name: &str = it
            .next()
            .ok_or_else(|| parse_err(path, line, "missing MODEL"))?;
        let model = Model::from_name(model_name).ok_or_else(|| ColmapError::UnknownModel {
            path: path.to_path_buf(),
            camera_id,
            model: format!("{model_name} (line {line})"),
        })?;
        let width: u64 = field(path, line, it.next(), "WIDTH")?;
        let height: u64 = field(path, line, it.next(), "HEIGHT")?;
        let params = it
            .map(|t| field::<f64>(path, line, Some(t), "parameter"))
            .collect::<Result<Vec<_>, _>>()?;
        let cam = make_camera(camera_id, model, width, height, &params)
            .map_err(|why| parse_err(path, line, format!("camera {camera_id}: {why}")))?;
        out.push(cam);
    }
    Ok(out)
}

fn parse_images_txt(path: &Path, text: &str) -> Result<Vec<RawImage>, ColmapError> {
    let mut out = Vec::new();
    let mut lines = text.lines().enumerate().map(|(i, l)| (i + 1, l.trim()));
    while let Some((line, l)) = lines.next() {
        if l.is_empty() || l.starts_with('#') {
            continue;
        }
        let mut it = l.split_whitespace();
        let image_id: u32 = field(path, line, it.next(), "IMAGE_ID")?;
        let mut q = [0.0; 4];
        for (v, name) in q.iter_mut().zip(["QW", "QX", "QY", "QZ"]) {
            *v = field(path, line, it.next(), name)?;
        }
        let mut t = [0.0; 3];
        for (v, name) in t.iter_mut().zip(["TX", "TY", "TZ"]) {
            *v = field(path, line, it.next(), name)?;
        }
        let camera_id: u32 = field(path, line, it.next(), "CAMERA_ID")?;
        // Names may contain spaces: the rest of the line.
        let rest: Vec<&str> = it.collect();
        if rest.is_empty() {
            return Err(parse_err(path, line, "missing NAME"));
        }
        let name = rest.join(" ");
        // The POINTS2D line follows (possibly empty); a missing one at EOF is tolerated.
        if let Some((pline, pts)) = lines.next() {
            let n = pts.split_whitespace().count();
            if n % 3 != 0 {
                return Err(parse_err(
                    path,
                    pline,
                    format!(
                        "image {image_id} ({name}): POINTS2D has {n} values, not a multiple of 3"
                    ),
                ));
            }
        }
        let pose = make_pose(q, t).map_err(|why| ColmapError::BadPose {
            path: path.to_path_buf(),
            line: Some(line),
            image_id,
            name: name.clone(),
            why,
        })?;
        out.push(RawImage {
            image_id,
            camera_id,
            name,
            pose,
        });
    }
    Ok(out)
}

fn parse_points_txt(path: &Path, text: &str) -> Result<Vec<Point3D>, ColmapError> {
    let mut out = Vec::new();
    for (line, l) in data_lines(text) {
        let mut it = l.split_whitespace();
        let id: u64 = field(path, line, it.next(), "POINT3D_ID")?;
        let mut xyz = [0.0; 3];
        for (v, n) in xyz.iter_mut().zip(["X", "Y", "Z"]) {
            *v = field(path, line, it.next(), n)?;
        }
        let mut rgb = [0u8; 3];
        for (v, n) in rgb.iter_mut().zip(["R", "G", "B"]) {
            *v = field(path, line, it.next(), n)?;
        }
        let error: f64 = field(path, line, it.next(), "ERROR")?;
        if it.count() % 2 != 0 {
            return Err(parse_err(path, line, "TRACK has an odd number of values"));
        }
        out.push(Point3D {
            id,
            xyz,
            rgb,
            error,
        });
    }
    Ok(out)
}

// ---------------------------------------------------------------- public API

/// The bytes of a text-format file as UTF-8 (a leading byte-order mark, as some Windows
/// editors write, skipped), or an error naming the line of the first bad byte.
fn utf8<'a>(path: &Path, bytes: &'a [u8]) -> Result<&'a str, ColmapError> {
    let bytes = bytes.strip_prefix("\u{feff}".as_bytes()).unwrap_or(bytes);
    std::str::from_utf8(bytes).map_err(|e| {
        let line = 1 + bytes[..e.valid_up_to()]
            .iter()
            .filter(|&&b| b == b'\n')
            .count();
        parse_err(path, line, "not UTF-8 text")
    })
}

/// Which format a model directory holds: `.bin` preferred, `.txt` as the fallback.
fn model_ext(dir: &Path) -> Result<&'static str, ColmapError> {
    for ext in ["bin", "txt"] {
        if dir.join(format!("cameras.{ext}")).is_file()
            && dir.join(format!("images.{ext}")).is_file()
        {
            return Ok(ext);
        }
    }
    Err(ColmapError::NoModel {
        dir: dir.to_path_buf(),
    })
}

/// Reads the cameras of a model directory.
pub fn read_cameras(sparse_dir: &Path) -> Result<Vec<ColmapCamera>, ColmapError> {
    let ext = model_ext(sparse_dir)?;
    let path = sparse_dir.join(format!("cameras.{ext}"));
    let bytes = read_file(&path)?;
    if ext == "bin" {
        parse_cameras_bin(&path, &bytes)
    } else {
        parse_cameras_txt(&path, utf8(&path, &bytes)?)
    }
}

/// Reads `points3D.bin` / `points3D.txt` (same format preference as [`read_model`]);
/// an empty list when the model has no points file.
pub fn read_points3d(sparse_dir: &Path) -> Result<Vec<Point3D>, ColmapError> {
    let ext = model_ext(sparse_dir)?;
    let path = sparse_dir.join(format!("points3D.{ext}"));
    if !path.is_file() {
        return Ok(Vec::new());
    }
    parse_points(&path, &read_file(&path)?, ext == "bin")
}

/// Parses the bytes of a `points3D.bin` (`binary`) or `points3D.txt`; `path` names it.
pub fn parse_points(path: &Path, bytes: &[u8], binary: bool) -> Result<Vec<Point3D>, ColmapError> {
    if binary {
        parse_points_bin(path, bytes)
    } else {
        parse_points_txt(path, utf8(path, bytes)?)
    }
}

/// Reads a COLMAP sparse model (`.bin` preferred, `.txt` as fallback) into views sorted
/// by image name.
pub fn read_model(sparse_dir: &Path) -> Result<Vec<View>, ColmapError> {
    let ext = model_ext(sparse_dir)?;
    let cam_path = sparse_dir.join(format!("cameras.{ext}"));
    let img_path = sparse_dir.join(format!("images.{ext}"));
    let (cam_bytes, img_bytes) = (read_file(&cam_path)?, read_file(&img_path)?);
    parse_model(&cam_path, &cam_bytes, &img_path, &img_bytes, ext == "bin")
}

/// [`read_model`] on the bytes of `cameras` and `images` (`.bin` when `binary`, else
/// `.txt`); the paths name them in errors.
pub fn parse_model(
    cam_path: &Path,
    cam_bytes: &[u8],
    img_path: &Path,
    img_bytes: &[u8],
    binary: bool,
) -> Result<Vec<View>, ColmapError> {
    let (cam_path, img_path) = (cam_path.to_path_buf(), img_path.to_path_buf());
    let (cameras, images) = if binary {
        (
            parse_cameras_bin(&cam_path, cam_bytes)?,
            parse_images_bin(&img_path, img_bytes)?,
        )
    } else {
        (
            parse_cameras_txt(&cam_path, utf8(&cam_path, cam_bytes)?)?,
            parse_images_txt(&img_path, utf8(&img_path, img_bytes)?)?,
        )
    };
    let mut by_id = std::collections::BTreeMap::new();
    for c in &cameras {
        if by_id.insert(c.camera_id, c).is_some() {
            return Err(ColmapError::Duplicate {
                path: cam_path,
                what: "camera",
                id: c.camera_id.into(),
            });
        }
    }
    let mut seen = std::collections::BTreeSet::new();
    let mut names: std::collections::HashMap<String, u32> = Default::default();
    let mut views = Vec::with_capacity(images.len());
    for img in images {
        if !seen.insert(img.image_id) {
            return Err(ColmapError::Duplicate {
                path: img_path,
                what: "image",
                id: img.image_id.into(),
            });
        }
        // `View::stem` names every per-view file: it must not be empty.
        let file = img.name.rsplit('/').next().unwrap_or(&img.name);
        if file.is_empty() || file == "." {
            return Err(ColmapError::NoStem {
                path: img_path,
                image_id: img.image_id,
                name: img.name,
            });
        }
        if let Some(&first) = names.get(&img.name) {
            return Err(ColmapError::DuplicateName {
                path: img_path,
                name: img.name,
                first,
                second: img.image_id,
            });
        }
        names.insert(img.name.clone(), img.image_id);
        let cam = by_id
            .get(&img.camera_id)
            .ok_or_else(|| ColmapError::MissingCamera {
                path: img_path.clone(),
                image_id: img.image_id,
                name: img.name.clone(),
                camera_id: img.camera_id,
            })?;
        views.push(View {
            image_id: img.image_id,
            camera_id: img.camera_id,
            name: img.name,
            camera: Camera {
                intrinsics: cam.intrinsics,
                pose: img.pose,
            },
        });
    }
    views.sort_by(|a, b| a.name.cmp(&b.name).then(a.image_id.cmp(&b.image_id)));
    Ok(views)
}

/// Writes `cameras`, `images` and an empty `points3D` in the binary or text format.
/// Views sharing a `camera_id` must share intrinsics; the first one's are written.
/// Each camera is written with the simplest model that represents it exactly.
pub fn write_model(dir: &Path, views: &[View], binary: bool) -> Result<(), ColmapError> {
    fsutil::create_dir(dir)?;
    let mut cams: std::collections::BTreeMap<u32, &camera::Intrinsics> = Default::default();
    for v in views {
        cams.entry(v.camera_id).or_insert(&v.camera.intrinsics);
    }
    let ext = if binary { "bin" } else { "txt" };
    let mut cam_out = Vec::new();
    let mut img_out = Vec::new();
    let points_out: Vec<u8>;
    if binary {
        cam_out.extend_from_slice(&(cams.len() as u64).to_le_bytes());
        for (id, k) in &cams {
            let (model, params) = Model::for_intrinsics(k);
            cam_out.extend_from_slice(&id.to_le_bytes());
            cam_out.extend_from_slice(&model.id().to_le_bytes());
            cam_out.extend_from_slice(&u64::from(k.width).to_le_bytes());
            cam_out.extend_from_slice(&u64::from(k.height).to_le_bytes());
            for p in params {
                cam_out.extend_from_slice(&p.to_le_bytes());
            }
        }
        img_out.extend_from_slice(&(views.len() as u64).to_le_bytes());
        for v in views {
            img_out.extend_from_slice(&v.image_id.to_le_bytes());
            for q in v.camera.pose.colmap_qvec() {
                img_out.extend_from_slice(&q.to_le_bytes());
            }
            for t in v.camera.pose.translation.to_array() {
                img_out.extend_from_slice(&t.to_le_bytes());
            }
            img_out.extend_from_slice(&v.camera_id.to_le_bytes());
            img_out.extend_from_slice(v.name.as_bytes());
            img_out.push(0);
            img_out.extend_from_slice(&0u64.to_le_bytes());
        }
        points_out = 0u64.to_le_bytes().to_vec();
    } else {
        let mut s = String::from(
            "# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n",
        );
        s.push_str(&format!("# Number of cameras: {}\n", cams.len()));
        for (id, k) in &cams {
            let (model, params) = Model::for_intrinsics(k);
            s.push_str(&format!("{id} {} {} {}", model.name(), k.width, k.height));
            for p in params {
                // `{:?}` prints the shortest representation that round-trips exactly.
                s.push_str(&format!(" {p:?}"));
            }
            s.push('\n');
        }
        cam_out = s.into_bytes();
        let mut s = String::from(
            "# Image list with two lines of data per image:\n#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n#   POINTS2D[] as (X, Y, POINT3D_ID)\n",
        );
        s.push_str(&format!("# Number of images: {}\n", views.len()));
        for v in views {
            let q = v.camera.pose.colmap_qvec();
            let t = v.camera.pose.translation;
            s.push_str(&format!(
                "{} {:?} {:?} {:?} {:?} {:?} {:?} {:?} {} {}\n\n",
                v.image_id, q[0], q[1], q[2], q[3], t.x, t.y, t.z, v.camera_id, v.name
            ));
        }
        img_out = s.into_bytes();
        points_out = b"# 3D point list with one line of data per point:\n#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n# Number of points: 0\n".to_vec();
    }
    fsutil::write_bytes(&dir.join(format!("cameras.{ext}")), &cam_out)?;
    fsutil::write_bytes(&dir.join(format!("images.{ext}")), &img_out)?;
    fsutil::write_bytes(&dir.join(format!("points3D.{ext}")), &points_out)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DVec3;

    fn tmpdir(tag: &str) -> PathBuf {
        let d = crate::fsutil::test_temp_dir()
            .join(format!("gs4city-colmap-{tag}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    fn views() -> Vec<View> {
        let dists = [
            (500.0, 500.0, Distortion::None),
            (500.0, 520.0, Distortion::None),
            (480.0, 480.0, Distortion::Radial { k1: -0.1, k2: 0.0 }),
            (480.0, 480.0, Distortion::Radial { k1: -0.1, k2: 0.02 }),
            (
                600.0,
                610.0,
                Distortion::OpenCv {
                    k1: -0.2,
                    k2: 0.05,
                    p1: 1e-3,
                    p2: -2e-4,
                },
            ),
            (
                600.0,
                601.0,
                Distortion::FullOpenCv {
                    k: [-0.2, 0.05, 0.01, 0.02, 0.003, 0.001],
                    p1: 1e-3,
                    p2: -2e-4,
                },
            ),
        ];
        dists
            .iter()
            .enumerate()
            .map(|(i, &(fx, fy, d))| View {
                image_id: 10 - i as u32,
                camera_id: i as u32 + 1,
                name: format!("sub dir/img_{i}.jpg"),
                camera: Camera {
                    intrinsics: Intrinsics {
                        width: 640 + i as u32,
                        height: 480,
                        fx,
                        fy,
                        cx: 320.25,
                        cy: 239.5,
                        distortion: d,
                    },
                    pose: Pose::look_at(
                        DVec3::new(i as f64 * 3.1, -7.0, 2.5),
                        DVec3::new(0.3, 0.1, 0.7),
                        DVec3::Z,
                    )
                    .unwrap(),
                },
            })
            .collect()
    }

    fn assert_same(a: &[View], b: &[View]) {
        assert_eq!(a.len(), b.len());
        for (x, y) in a.iter().zip(b) {
            assert_eq!(x.name, y.name);
            assert_eq!(x.image_id, y.image_id);
            assert_eq!(x.camera_id, y.camera_id);
            assert_eq!(x.camera.intrinsics, y.camera.intrinsics);
            let d = (x.camera.pose.rotation - y.camera.pose.rotation)
                .to_cols_array()
                .iter()
                .fold(0.0f64, |m, v| m.max(v.abs()));
            assert!(d < 1e-12, "rotation differs by {d}");
            assert!((x.camera.pose.translation - y.camera.pose.translation).length() < 1e-12);
        }
    }

    #[test]
    fn round_trip_text_and_binary() {
        let vs = views();
        for binary in [false, true] {
            let dir = tmpdir(if binary { "rtb" } else { "rtt" });
            write_model(&dir, &vs, binary).unwrap();
            let back = read_model(&dir).unwrap();
            assert_same(&vs, &back);
            assert!(read_points3d(&dir).unwrap().is_empty());
            let cams = read_cameras(&dir).unwrap();
            let models: Vec<&str> = cams.iter().map(|c| c.model.name()).collect();
            assert_eq!(
                models,
                [
                    "SIMPLE_PINHOLE",
                    "PINHOLE",
                    "SIMPLE_RADIAL",
                    "RADIAL",
                    "OPENCV",
                    "FULL_OPENCV"
                ]
            );
        }
    }

    #[test]
    fn prefers_binary_and_sorts_by_name() {
        let dir = tmpdir("pref");
        let mut vs = views();
        write_model(&dir, &vs[..2], false).unwrap();
        vs.reverse();
        write_model(&dir, &vs, true).unwrap();
        let back = read_model(&dir).unwrap();
        assert_eq!(back.len(), 6);
        assert!(back.windows(2).all(|w| w[0].name < w[1].name));
    }

    #[test]
    fn text_reader_handles_comments_points_and_reports_lines() {
        let dir = tmpdir("txt");
        std::fs::write(
            dir.join("cameras.txt"),
            "# c\n\n1 PINHOLE 100 80 90 91 50 40\n",
        )
        .unwrap();
        std::fs::write(
            dir.join("images.txt"),
            "# header\n1 1 0 0 0 0 0 0 1 a.png\n1.0 2.0 -1 3 4 7\n2 1 0 0 0 1 2 3 1 b.png\n\n",
        )
        .unwrap();
        std::fs::write(
            dir.join("points3D.txt"),
            "# p\n7 1 2 3 255 0 10 0.5 1 0 2 1\n",
        )
        .unwrap();
        let v = read_model(&dir).unwrap();
        assert_eq!(v.len(), 2);
        assert_eq!(v[1].camera.pose.translation, DVec3::new(1.0, 2.0, 3.0));
        let p = read_points3d(&dir).unwrap();
        assert_eq!(p[0].id, 7);
        assert_eq!(p[0].rgb, [255, 0, 10]);

        std::fs::write(
            dir.join("images.txt"),
            "# header\n1 1 0 0 0 0 0 0 1 a.png\n\n5 0 0 0 0 0 0 0 1 zero.png\n\n",
        )
        .unwrap();
        let e = read_model(&dir).unwrap_err().to_string();
        assert!(
            e.contains("image 5") && e.contains("zero.png") && e.contains("images.txt:4:"),
            "{e}"
        );

        std::fs::write(dir.join("images.txt"), "1 1 0 0 0 0 0 0 9 a.png\n\n").unwrap();
        let e = read_model(&dir).unwrap_err().to_string();
        assert!(e.contains("camera 9") && e.contains("a.png"), "{e}");

        // A byte-order mark before the first line (Windows editors) is skipped, and a
        // quaternion whose squares overflow is the rotation of its direction.
        std::fs::write(
            dir.join("cameras.txt"),
            "\u{feff}1 PINHOLE 100 80 90 91 50 40\n",
        )
        .unwrap();
        std::fs::write(
            dir.join("images.txt"),
            "\u{feff}# header\n1 1e200 1e200 0 0 0 0 0 1 a.png\n\n2 1 1 0 0 0 0 0 1 b.png\n\n",
        )
        .unwrap();
        let v = read_model(&dir).unwrap();
        assert_eq!(v[0].camera.intrinsics.fx, 90.0);
        assert_eq!(v[0].camera.pose.rotation, v[1].camera.pose.rotation);
        let quarter_turn_x = glam::DMat3::from_rotation_x(std::f64::consts::FRAC_PI_2);
        assert!(v[0].camera.pose.rotation.abs_diff_eq(quarter_turn_x, 1e-15));

        std::fs::write(dir.join("images.txt"), "1 1 0 0 nan 0 0 0 1 a.png\n\n").unwrap();
        let e = read_model(&dir).unwrap_err();
        assert!(matches!(e, ColmapError::BadPose { image_id: 1, .. }), "{e}");

        std::fs::write(dir.join("images.txt"), "1 1 0 0 0 0 0 x 1 a.png\n\n").unwrap();
        let e = read_model(&dir).unwrap_err().to_string();
        assert!(e.contains("images.txt:1") && e.contains("TZ"), "{e}");

        std::fs::write(dir.join("cameras.txt"), "\n\n1 FISHEYE_X 100 80 1 2 3\n").unwrap();
        let e = read_model(&dir).unwrap_err().to_string();
        assert!(
            e.contains("FISHEYE_X") && e.contains("line 3") && e.contains("cameras.txt"),
            "{e}"
        );

        std::fs::write(dir.join("cameras.txt"), "1 PINHOLE 100 80 90 91 50\n").unwrap();
        let e = read_model(&dir).unwrap_err().to_string();
        assert!(e.contains("4 parameters") && e.contains(":1:"), "{e}");
    }

    #[test]
    fn truncated_and_missing_binary_files_are_errors() {
        let dir = tmpdir("trunc");
        assert!(matches!(
            read_model(&dir).unwrap_err(),
            ColmapError::NoModel { .. }
        ));
        write_model(&dir, &views(), true).unwrap();
        let full = std::fs::read(dir.join("images.bin")).unwrap();
        for cut in [0, 5, 8, 40, full.len() - 9, full.len() - 1] {
            std::fs::write(dir.join("images.bin"), &full[..cut]).unwrap();
            let e = read_model(&dir).unwrap_err();
            assert!(matches!(e, ColmapError::Truncated { .. }), "cut {cut}: {e}");
            assert!(e.to_string().contains("images.bin"));
        }
        // A huge count must not allocate: it is reported as truncation.
        let mut huge = u64::MAX.to_le_bytes().to_vec();
        huge.extend_from_slice(&[0; 16]);
        std::fs::write(dir.join("images.bin"), &huge).unwrap();
        assert!(matches!(
            read_model(&dir).unwrap_err(),
            ColmapError::Truncated { .. }
        ));
        std::fs::write(dir.join("images.bin"), &full).unwrap();
        let cams = std::fs::read(dir.join("cameras.bin")).unwrap();
        let mut bad = cams.clone();
        bad[12..16].copy_from_slice(&5i32.to_le_bytes()); // OPENCV_FISHEYE: unsupported
        std::fs::write(dir.join("cameras.bin"), &bad).unwrap();
        assert!(matches!(
            read_model(&dir).unwrap_err(),
            ColmapError::UnknownModel { camera_id: 1, .. }
        ));
    }
}
