//! Georeferencing through PROJ (the system libproj, by the `proj` crate): a city model's CRS
//! (its `srsName`, or `--crs`) → geographic longitude/latitude → Earth-centred, Earth-fixed
//! (ECEF, EPSG:4978 = WGS 84 geocentric) coordinates, and the local east-north-up frame of a
//! point, all in f64. The 3D Tiles export places its tiles on the globe with these.
//!
//! PROJ does the projection and the datum work: `CRS → EPSG:4326` (axis order normalised to
//! longitude, latitude) and the geodetic → geocentric conversion `+proj=cart +ellps=WGS84`.
//! The `proj` crate's `convert` is two-dimensional (it passes a height of 0 and returns x, y),
//! so the geocentric point is asked for twice — `(X, Y)`, then `(Z, X)` through an
//! `axisswap` step — at height 0, and the height `h` is added along the ellipsoid normal
//! `n(λ, φ) = (cos φ cos λ, cos φ sin λ, sin φ)`: exact for ellipsoidal heights, since a
//! point at height `h` lies on the normal through its foot point. A CRS whose height axis is
//! orthometric (a compound CRS) is reduced at height 0 by PROJ (the geoid there, where PROJ
//! has its grid) and carried along the normal from there.
use glam::{DMat3, DVec3};
use proj::Proj;

use crate::numfmt::Num;

/// Errors of the georeferencing.
#[derive(Debug, thiserror::Error)]
pub enum CrsError {
    /// PROJ does not know the CRS.
    #[error(
        "CRS `{crs}`: PROJ does not know it ({why}); give an EPSG code PROJ knows, e.g. --crs EPSG:25832"
    )]
    Unknown { crs: String, why: String },
    /// A coordinate PROJ could not transform.
    #[error("CRS `{crs}`: PROJ cannot transform ({}, {}): {why}", Num(*x), Num(*y))]
    Transform {
        crs: String,
        x: f64,
        y: f64,
        why: String,
    },
}

/// The German AdV names of `srsName` (`urn:adv:crs:…`) that PROJ does not resolve, with the
/// EPSG code of their horizontal CRS (heights are then taken as ellipsoidal).
const ADV: [(&str, &str); 4] = [
    ("ETRS89_UTM32", "EPSG:25832"),
    ("ETRS89_UTM33", "EPSG:25833"),
    ("DE_DHDN_3GK3", "EPSG:31467"),
    ("DE_DHDN_3GK4", "EPSG:31468"),
];

/// The EPSG codes named in `srs` (`EPSG:25832`, `urn:ogc:def:crs:EPSG::25832`,
/// `…/def/crs/EPSG/0/25832`, a compound URN): `EPSG:a` or `EPSG:a+b`.
fn epsg_codes(srs: &str) -> Option<String> {
    let up = srs.to_ascii_uppercase();
    let mut codes = Vec::new();
    let mut rest = up.as_str();
    while let Some(i) = rest.find("EPSG") {
        rest = &rest[i + 4..];
        let mut tail = rest.trim_start_matches([':', '/']);
        if let Some(t) = tail.strip_prefix("0/") {
            tail = t; // the version segment of an OGC URL (…/EPSG/0/25832)
        }
        let digits: String = tail.chars().take_while(char::is_ascii_digit).collect();
        if !digits.is_empty() {
            codes.push(digits);
        }
    }
    match codes.len() {
        0 => None,
        _ => Some(format!("EPSG:{}", codes.join("+"))),
    }
}

/// The names to offer PROJ for a `srsName`, best first: the EPSG codes it names (`EPSG:a` or
/// `EPSG:a+b`), else an AdV name's horizontal CRS, else the name itself. A name PROJ cannot
/// resolve makes PROJ log a line of its own, so a name with an EPSG code in it is offered as
/// that code alone.
pub fn candidates(srs: &str) -> Vec<String> {
    if let Some(e) = epsg_codes(srs) {
        return vec![e];
    }
    let up = srs.to_ascii_uppercase();
    let mut out: Vec<String> = ADV
        .iter()
        .filter(|(name, _)| up.contains(name))
        .map(|(_, epsg)| epsg.to_string())
        .collect();
    if out.is_empty() {
        out.push(srs.trim().to_string());
    }
    out.dedup();
    out
}

/// PROJ's database `proj.db`: in `$PROJ_DATA` or `$PROJ_LIB` (`:`-separated), else the
/// system's `/usr/share/proj` or `/usr/local/share/proj`.
fn proj_db() -> Option<std::path::PathBuf> {
    let mut dirs: Vec<std::path::PathBuf> = Vec::new();
    for var in ["PROJ_DATA", "PROJ_LIB"] {
        if let Some(v) = std::env::var_os(var) {
            dirs.extend(std::env::split_paths(&v));
        }
    }
    dirs.push("/usr/share/proj".into());
    dirs.push("/usr/local/share/proj".into());
    dirs.into_iter()
        .map(|d| d.join("proj.db"))
        .find(|p| p.is_file())
}

/// For a name `EPSG:a` or `EPSG:a+b`: the first code that PROJ's database does not hold (so
/// PROJ is not asked, and does not log a line of its own), with the database's path. `None`
/// when every code is there, the name is of another form, or the database cannot be read (PROJ
/// then decides).
fn missing_epsg(name: &str) -> Option<(String, std::path::PathBuf)> {
    let codes = name.strip_prefix("EPSG:")?;
    let db = proj_db()?;
    let conn =
        rusqlite::Connection::open_with_flags(&db, rusqlite::OpenFlags::SQLITE_OPEN_READ_ONLY)
            .ok()?;
    for code in codes.split('+') {
        let n: i64 = conn
            .query_row(
                "SELECT count(*) FROM crs_view WHERE auth_name = 'EPSG' AND code = ?1",
                [code],
                |r| r.get(0),
            )
            .ok()?;
        if n == 0 {
            return Some((format!("EPSG:{code}"), db));
        }
    }
    None
}

/// A CRS and the PROJ operations that take its coordinates to the globe.
pub struct Georef {
    /// The name PROJ accepted.
    pub crs: String,
    to_lonlat: Proj,
    from_lonlat: Proj,
    cart_xy: Proj,
    cart_zx: Proj,
}

impl std::fmt::Debug for Georef {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Georef").field("crs", &self.crs).finish()
    }
}

impl Georef {
    /// The operations of CRS `srs` (an `srsName`, an EPSG code, any name PROJ resolves;
    /// [`candidates`] are tried in turn).
    pub fn new(srs: &str) -> Result<Georef, CrsError> {
        let mut why = String::new();
        for name in candidates(srs) {
            if let Some((code, db)) = missing_epsg(&name) {
                if why.is_empty() {
                    why = format!("{code} is not in its database {}", db.display());
                }
                continue;
            }
            match Proj::new_known_crs(&name, "EPSG:4326", None) {
                Ok(to_lonlat) => {
                    let from_lonlat =
                        Proj::new_known_crs("EPSG:4326", &name, None).map_err(|e| {
                            CrsError::Unknown {
                                crs: name.clone(),
                                why: format!("the projection from longitude/latitude: {e}"),
                            }
                        })?;
                    let cart = |tail: &str| {
                        Proj::new(&format!(
                            "+proj=pipeline +step +proj=unitconvert +xy_in=deg +xy_out=rad \
                             +step +proj=cart +ellps=WGS84{tail}"
                        ))
                        .map_err(|e| CrsError::Unknown {
                            crs: name.clone(),
                            why: format!("the geocentric conversion: {e}"),
                        })
                    };
                    return Ok(Georef {
                        crs: name.clone(),
                        to_lonlat,
                        from_lonlat,
                        cart_xy: cart("")?,
                        cart_zx: cart(" +step +proj=axisswap +order=3,1,2")?,
                    });
                }
                Err(e) if why.is_empty() => why = e.to_string(),
                Err(_) => {}
            }
        }
        Err(CrsError::Unknown {
            crs: srs.to_string(),
            why,
        })
    }

    fn fail(&self, x: f64, y: f64, why: impl std::fmt::Display) -> CrsError {
        CrsError::Transform {
            crs: self.crs.clone(),
            x,
            y,
            why: why.to_string(),
        }
    }

    /// Longitude and latitude (degrees, WGS 84) of CRS point `(x, y)`.
    pub fn lon_lat(&self, x: f64, y: f64) -> Result<(f64, f64), CrsError> {
        let (lon, lat) = self
            .to_lonlat
            .convert((x, y))
            .map_err(|e| self.fail(x, y, e))?;
        if !(lon.is_finite() && lat.is_finite() && lat.abs() <= 90.0) {
            return Err(self.fail(
                x,
                y,
                format!("longitude {}, latitude {}", Num(lon), Num(lat)),
            ));
        }
        Ok((lon, lat))
    }

    /// The CRS point `(x, y)` of a longitude and latitude (degrees, WGS 84); heights are not
    /// converted (a photo's GPS altitude is taken as the CRS's height: the difference between
    /// datums is far below a phone's altitude error).
    pub fn xy(&self, lon: f64, lat: f64) -> Result<(f64, f64), CrsError> {
        let (x, y) = self
            .from_lonlat
            .convert((lon, lat))
            .map_err(|e| self.fail(lon, lat, e))?;
        if !(x.is_finite() && y.is_finite()) {
            return Err(self.fail(lon, lat, format!("gives ({}, {})", Num(x), Num(y))));
        }
        Ok((x, y))
    }

    /// ECEF (EPSG:4978, metres) of CRS point `p` (`p.z` the height; module docs).
    pub fn ecef(&self, p: DVec3) -> Result<DVec3, CrsError> {
        let (lon, lat) = self.lon_lat(p.x, p.y)?;
        let (x, y) = self
            .cart_xy
            .convert((lon, lat))
            .map_err(|e| self.fail(p.x, p.y, e))?;
        let (z, x2) = self
            .cart_zx
            .convert((lon, lat))
            .map_err(|e| self.fail(p.x, p.y, e))?;
        debug_assert!((x - x2).abs() < 1e-6);
        Ok(DVec3::new(x, y, z) + p.z * up(lon, lat))
    }
}

/// The ellipsoid normal (local up) at longitude/latitude in degrees, in ECEF.
pub fn up(lon_deg: f64, lat_deg: f64) -> DVec3 {
    let (sl, cl) = lon_deg.to_radians().sin_cos();
    let (sp, cp) = lat_deg.to_radians().sin_cos();
    DVec3::new(cp * cl, cp * sl, sp)
}

/// The east-north-up frame at longitude/latitude (degrees): its columns are east, north and
/// up in ECEF (the frame 3D Tiles and CesiumJS call `eastNorthUpToFixedFrame`).
pub fn enu_frame(lon_deg: f64, lat_deg: f64) -> DMat3 {
    let (sl, cl) = lon_deg.to_radians().sin_cos();
    let (sp, cp) = lat_deg.to_radians().sin_cos();
    DMat3::from_cols(
        DVec3::new(-sl, cl, 0.0),
        DVec3::new(-sp * cl, -sp * sl, cp),
        DVec3::new(cp * cl, cp * sl, sp),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn srs_names_give_epsg_codes() {
        assert_eq!(epsg_codes("EPSG:32632").as_deref(), Some("EPSG:32632"));
        assert_eq!(
            epsg_codes("urn:ogc:def:crs:EPSG::25832").as_deref(),
            Some("EPSG:25832")
        );
        assert_eq!(
            epsg_codes("http://www.opengis.net/def/crs/EPSG/0/25832").as_deref(),
            Some("EPSG:25832")
        );
        assert_eq!(
            epsg_codes("urn:ogc:def:crs,crs:EPSG::25832,crs:EPSG::7837").as_deref(),
            Some("EPSG:25832+7837")
        );
        assert_eq!(epsg_codes("urn:adv:crs:ETRS89_UTM32*DE_DHHN92_NH"), None);
        assert_eq!(
            candidates("urn:adv:crs:ETRS89_UTM32*DE_DHHN92_NH"),
            vec!["EPSG:25832".to_string()]
        );
        assert_eq!(
            candidates("urn:ogc:def:crs:EPSG::25832"),
            vec!["EPSG:25832".to_string()]
        );
        assert_eq!(candidates(" WGS 84 "), vec!["WGS 84".to_string()]);
    }

    #[test]
    fn enu_frame_is_a_rotation_with_up_outward() {
        let f = enu_frame(9.2, 48.7);
        assert!((f.determinant() - 1.0).abs() < 1e-12);
        assert!((f.transpose() * f - DMat3::IDENTITY).abs_diff_eq(DMat3::ZERO, 1e-12));
        assert!((f.z_axis - up(9.2, 48.7)).length() < 1e-15);
    }
}
