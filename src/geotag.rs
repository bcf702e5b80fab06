//! Georeferencing a capture from its photos' GPS (`gs4city align --exif`, docs/align-exif.md):
//! the EXIF GPS position of each registered image (kamadak-exif) → the CRS through PROJ
//! ([`crate::crs`], `Georef::xy`) → a robust similarity from the COLMAP camera centres to those positions
//! ([`alignment::estimate_robust`]) → `alignment.json`.
//!
//! **The vertical.** A phone's GPS altitude is poor (its error is several metres, often more
//! than the height differences along a street), so it does not tilt the fit when the cameras
//! say where up is: photos are taken with the camera's image rows level (no roll), and
//! upright on average. The scene's up is then the direction perpendicular to every camera's
//! image-right axis where those span a plane (cameras looking in varied directions; exact
//! for level photos whatever their pitch), else the cameras' mean image-up with the common
//! right axis projected out (a constant pitch then tilts the result by that pitch). The
//! EXIF orientation says which image axis is up (landscape or portrait). The fit is then a
//! horizontal similarity (scale, heading, offset) from the positions and one vertical offset,
//! the median of the altitude residuals: altitude errors move the model up or down, never
//! tilt it. Where the cameras do not agree on an up (a nadir drone survey with one heading,
//! rolled photos), the full 3D similarity is fitted to positions and altitudes, and the
//! output says so. `align --refine` against the city model corrects what GPS cannot.
use std::path::{Path, PathBuf};

use glam::{DMat3, DVec3};

use crate::alignment::{self, AlignError, RobustFit, Vertical};
use crate::camera::View;
use crate::crs::{CrsError, Georef};

/// Errors of georeferencing from GPS; each names its file.
#[derive(Debug, thiserror::Error)]
pub enum GeotagError {
    #[error("{path}: EXIF: {why}")]
    Exif { path: PathBuf, why: String },
    #[error("{0}")]
    Crs(#[from] CrsError),
    #[error(transparent)]
    Align(#[from] AlignError),
    #[error("{dir}: {why}")]
    Scene { dir: PathBuf, why: String },
}

/// The GPS fix of one photo (WGS 84).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GpsFix {
    pub lat_deg: f64,
    pub lon_deg: f64,
    /// Metres above sea level (EXIF `GPSAltitude`, negative below with `GPSAltitudeRef` 1).
    pub alt_m: Option<f64>,
}

/// What the EXIF of one photo says: its GPS fix (`None` without one) and its orientation
/// tag (1 when absent).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PhotoTags {
    pub gps: Option<GpsFix>,
    pub orientation: u16,
}

fn rational_deg(f: &exif::Field) -> Option<f64> {
    match &f.value {
        exif::Value::Rational(v) if !v.is_empty() => {
            let mut deg = 0.0;
            for (r, unit) in v.iter().zip([1.0, 60.0, 3600.0]) {
                if r.denom == 0 {
                    return None;
                }
                deg += r.to_f64() / unit;
            }
            Some(deg)
        }
        _ => None,
    }
}

fn ascii_first(f: &exif::Field) -> Option<u8> {
    match &f.value {
        exif::Value::Ascii(v) => v.first().and_then(|s| s.first()).copied(),
        _ => None,
    }
}

/// Reads a photo's EXIF GPS fix and orientation. A photo without EXIF, or without GPS tags,
/// gives no fix; a fix at exactly 0° N 0° E (what some cameras write without one) is no fix;
/// a malformed GPS tag is an error naming the file and the tag.
pub fn read_tags(path: &Path) -> Result<PhotoTags, GeotagError> {
    let err = |why: String| GeotagError::Exif {
        path: path.to_path_buf(),
        why,
    };
    let file = std::fs::File::open(path).map_err(|e| err(e.to_string()))?;
    let exif = match exif::Reader::new().read_from_container(&mut std::io::BufReader::new(file)) {
        Ok(x) => x,
        Err(exif::Error::NotFound(_)) => {
            return Ok(PhotoTags {
                gps: None,
                orientation: 1,
            });
        }
        Err(e) => return Err(err(e.to_string())),
    };
    let get = |t: exif::Tag| exif.get_field(t, exif::In::PRIMARY);
    let orientation = get(exif::Tag::Orientation)
        .and_then(|f| f.value.get_uint(0))
        .map_or(1, |v| v as u16);
    let (Some(lat), Some(lon)) = (get(exif::Tag::GPSLatitude), get(exif::Tag::GPSLongitude)) else {
        return Ok(PhotoTags {
            gps: None,
            orientation,
        });
    };
    let mut lat_deg = rational_deg(lat).ok_or_else(|| {
        err(format!(
            "GPSLatitude {} is not a D/M/S rational",
            lat.display_value()
        ))
    })?;
    let mut lon_deg = rational_deg(lon).ok_or_else(|| {
        err(format!(
            "GPSLongitude {} is not a D/M/S rational",
            lon.display_value()
        ))
    })?;
    match get(exif::Tag::GPSLatitudeRef).and_then(ascii_first) {
        Some(b'S') => lat_deg = -lat_deg,
        Some(b'N') | None => {}
        Some(c) => {
            return Err(err(format!(
                "GPSLatitudeRef is {:?}, not N or S",
                c as char
            )));
        }
    }
    match get(exif::Tag::GPSLongitudeRef).and_then(ascii_first) {
        Some(b'W') => lon_deg = -lon_deg,
        Some(b'E') | None => {}
        Some(c) => {
            return Err(err(format!(
                "GPSLongitudeRef is {:?}, not E or W",
                c as char
            )));
        }
    }
    if !(lat_deg.abs() <= 90.0 && lon_deg.abs() <= 180.0) {
        return Err(err(format!(
            "GPS position {lat_deg}° N {lon_deg}° E is not on the globe"
        )));
    }
    if lat_deg == 0.0 && lon_deg == 0.0 {
        return Ok(PhotoTags {
            gps: None,
            orientation,
        });
    }
    let alt_m = match get(exif::Tag::GPSAltitude) {
        Some(f) => match &f.value {
            exif::Value::Rational(v) if !v.is_empty() && v[0].denom != 0 => {
                let below = get(exif::Tag::GPSAltitudeRef)
                    .and_then(|f| f.value.get_uint(0))
                    .is_some_and(|r| r == 1);
                let a = v[0].to_f64();
                Some(if below { -a } else { a })
            }
            _ => {
                return Err(err(format!(
                    "GPSAltitude {} is not a rational",
                    f.display_value()
                )));
            }
        },
        None => None,
    };
    Ok(PhotoTags {
        gps: Some(GpsFix {
            lat_deg,
            lon_deg,
            alt_m,
        }),
        orientation,
    })
}

/// The WGS 84 / UTM zone of a longitude/latitude: `EPSG:326zz` north, `EPSG:327zz` south (the
/// CRS used when the scene has no city model to take one from).
pub fn utm_crs(lon_deg: f64, lat_deg: f64) -> String {
    let zone = (((lon_deg + 180.0) / 6.0).floor() as i64).clamp(0, 59) + 1;
    let base = if lat_deg >= 0.0 { 32600 } else { 32700 };
    format!("EPSG:{}", base + zone)
}

/// The image's right and up axes in the camera frame (COLMAP: x right, y down in the stored
/// pixels) for EXIF orientation `o`: 1 as stored, 3 turned 180°, 6 and 8 portrait (the stored
/// image turned 90° clockwise, anticlockwise, for display); mirrored orientations as 1.
pub fn image_axes(o: u16) -> (DVec3, DVec3) {
    match o {
        3 => (DVec3::NEG_X, DVec3::Y),
        6 => (DVec3::NEG_Y, DVec3::NEG_X),
        8 => (DVec3::Y, DVec3::X),
        _ => (DVec3::X, DVec3::NEG_Y),
    }
}

/// The scene's up from the cameras, or `None` when they do not say (module docs): `rights`
/// and `ups` are each camera's image-right and image-up axes in the scene frame.
pub fn cameras_up(rights: &[DVec3], ups: &[DVec3], views: &[DVec3]) -> Option<DVec3> {
    let n = rights.len() as f64;
    if rights.is_empty() {
        return None;
    }
    let m = ups.iter().copied().sum::<DVec3>() / n;
    let scatter = rights.iter().fold(DMat3::ZERO, |s, r| {
        s + DMat3::from_cols(*r * r.x, *r * r.y, *r * r.z)
    }) / n;
    let (vals, vecs) = alignment::symmetric_eigen3(&scatter);
    // vals descending; the right axes span a plane when the second is not small
    let up = if vals[1] >= 0.05 {
        vecs[2]
    } else {
        let e1 = vecs[0];
        let p = m - m.dot(e1) * e1;
        if p.length() < 0.5 {
            return None;
        }
        p
    }
    .normalize();
    // the sign: along the mean image-up where photos are upright, else against the mean
    // viewing direction (a nadir camera looks down)
    let look = views.iter().copied().sum::<DVec3>() / n;
    let s = if up.dot(m).abs() >= 0.5 {
        up.dot(m)
    } else {
        -up.dot(look)
    };
    if s.abs() < 0.3 {
        return None;
    }
    // every camera's image-right is near level (|sin| of its tilt below 0.5, 30°)
    if rights.iter().any(|r| r.dot(up).abs() > 0.5) {
        return None;
    }
    Some(up * s.signum())
}

/// One registered image with a GPS fix.
#[derive(Debug, Clone)]
pub struct Camera {
    pub name: String,
    /// The camera centre in the scene frame.
    pub scene: DVec3,
    /// The GPS position in the CRS (x, y, height).
    pub geo: DVec3,
    pub fix: GpsFix,
}

/// The result of [`fit`].
#[derive(Debug, Clone)]
pub struct ExifFit {
    /// The CRS of the geo positions.
    pub crs: String,
    /// Where the CRS came from.
    pub crs_source: String,
    pub cameras: Vec<Camera>,
    /// Registered images without a usable GPS fix.
    pub without_gps: Vec<String>,
    pub fit: RobustFit,
}

/// Fits the alignment of `views` (a COLMAP model of `images/`) to their photos' GPS in `crs`
/// (else the UTM zone of their mean position; module docs).
pub fn fit(
    images: &Path,
    views: &[View],
    crs: Option<(&str, &str)>,
) -> Result<ExifFit, GeotagError> {
    let mut tagged = Vec::new();
    let mut without_gps = Vec::new();
    for v in views {
        let path = images.join(&v.name);
        if !path.is_file() {
            return Err(GeotagError::Scene {
                dir: images.to_path_buf(),
                why: format!("no photo {} for the COLMAP image of that name", v.name),
            });
        }
        let tags = read_tags(&path)?;
        match tags.gps {
            Some(g) if g.alt_m.is_some() => tagged.push((v, g, tags.orientation)),
            _ => without_gps.push(v.name.clone()),
        }
    }
    if tagged.len() < 3 {
        return Err(GeotagError::Scene {
            dir: images.to_path_buf(),
            why: format!(
                "{} of {} registered photos have a GPS position with altitude; at least 3 are needed",
                tagged.len(),
                views.len()
            ),
        });
    }
    let (crs, crs_source) = match crs {
        Some((c, src)) => (c.to_string(), src.to_string()),
        None => {
            let n = tagged.len() as f64;
            let lon = tagged.iter().map(|t| t.1.lon_deg).sum::<f64>() / n;
            let lat = tagged.iter().map(|t| t.1.lat_deg).sum::<f64>() / n;
            (
                utm_crs(lon, lat),
                "the UTM zone of the photos (the scene has no city model CRS)".to_string(),
            )
        }
    };
    let georef = Georef::new(&crs)?;
    let mut cameras = Vec::with_capacity(tagged.len());
    let (mut rights, mut ups, mut looks) = (Vec::new(), Vec::new(), Vec::new());
    for (v, g, o) in &tagged {
        let (x, y) = georef.xy(g.lon_deg, g.lat_deg)?;
        let pose = &v.camera.pose;
        let to_world = pose.rotation.transpose();
        let (r, u) = image_axes(*o);
        rights.push(to_world * r);
        ups.push(to_world * u);
        looks.push(to_world * DVec3::Z);
        cameras.push(Camera {
            name: v.name.clone(),
            scene: pose.center(),
            geo: DVec3::new(x, y, g.alt_m.unwrap_or(0.0)),
            fix: *g,
        });
    }
    let vertical = match cameras_up(&rights, &ups, &looks) {
        Some(up) => Vertical::Level(up),
        None => Vertical::Free,
    };
    let pairs: Vec<(DVec3, DVec3)> = cameras.iter().map(|c| (c.geo, c.scene)).collect();
    let fit = alignment::estimate_robust(images, &pairs, vertical)?;
    Ok(ExifFit {
        crs,
        crs_source,
        cameras,
        without_gps,
        fit,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn utm_zones() {
        assert_eq!(utm_crs(13.19, 55.69), "EPSG:32633");
        assert_eq!(utm_crs(-0.1, 51.5), "EPSG:32630");
        assert_eq!(utm_crs(151.2, -33.9), "EPSG:32756");
        assert_eq!(utm_crs(180.0, 10.0), "EPSG:32660");
    }

    #[test]
    fn the_up_of_level_cameras_is_found_whatever_their_pitch() {
        // scene frame: up is −y (a COLMAP-like frame); cameras level, headings all round,
        // pitched up by 20°: the right axes span the horizontal plane
        let up = DVec3::NEG_Y;
        let (mut r, mut u, mut l) = (Vec::new(), Vec::new(), Vec::new());
        for k in 0..8 {
            let h = k as f64 * 0.7;
            let fwd = DVec3::new(h.cos(), 0.0, h.sin());
            let right = fwd.cross(up).normalize() * -1.0;
            let p = 20f64.to_radians();
            let view = fwd * p.cos() + up * p.sin();
            let img_up = right.cross(view).normalize() * -1.0;
            r.push(right);
            u.push(img_up);
            l.push(view);
        }
        // image-up must point up, image-right ⊥ up
        assert!(u[0].dot(up) > 0.9 && r[0].dot(up).abs() < 1e-12);
        let got = cameras_up(&r, &u, &l).unwrap();
        assert!((got - up).length() < 1e-9, "{got}");
        // one heading only, pitch 0: the mean image-up
        let got = cameras_up(&r[..1], &[up], &l[..1]).unwrap();
        assert!((got - up).length() < 1e-9);
        // one camera rolled by 90° (its right axis up) among level ones: no up (a whole
        // capture rolled alike cannot be told from a level one without gravity)
        let (mut r2, mut u2) = (r.clone(), u.clone());
        r2[3] = up;
        u2[3] = r[3];
        assert!(cameras_up(&r2, &u2, &l).is_none());
    }
}
