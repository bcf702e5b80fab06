//! Units of attribute comparisons: a number in a query may carry a unit (`measuredHeight > 1200 cm`);
//! it is converted to the entity's unit (`<name>.uom` in `semantics.json`) when both are known
//! units of the same quantity. Unit strings of CityGML files are often URNs or references
//! (`urn:ogc:def:uom:UCUM::m`, `#m`): the part after the last `:` or `#` is used.

/// Units the grammar accepts after a number.
pub const KNOWN: [&str; 17] = [
    "mm", "cm", "dm", "m", "km", "in", "ft", "yd", "mi", "m2", "m²", "km2", "ha", "m3", "m³",
    "deg", "rad",
];

/// The quantity a unit measures and its factor to the base unit (metre, square metre, cubic
/// metre, radian).
fn factor(unit: &str) -> Option<(&'static str, f64)> {
    Some(match unit {
        "mm" => ("length", 1e-3),
        "cm" => ("length", 1e-2),
        "dm" => ("length", 1e-1),
        "m" => ("length", 1.0),
        "km" => ("length", 1e3),
        "in" => ("length", 0.0254),
        "ft" => ("length", 0.3048),
        "yd" => ("length", 0.9144),
        "mi" => ("length", 1609.344),
        "m2" | "m²" => ("area", 1.0),
        "km2" => ("area", 1e6),
        "ha" => ("area", 1e4),
        "m3" | "m³" => ("volume", 1.0),
        "deg" => ("angle", std::f64::consts::PI / 180.0),
        "rad" => ("angle", 1.0),
        _ => return None,
    })
}

/// The unit of a CityGML `uom` string (`urn:ogc:def:uom:UCUM::m` → `m`, `#m` → `m`).
pub fn normalise(uom: &str) -> &str {
    let u = uom.trim();
    let u = u.rsplit([':', '#', '/']).next().unwrap_or(u);
    match u {
        "metre" | "meter" | "metres" | "meters" => "m",
        "degree" | "degrees" => "deg",
        "sqm" => "m2",
        x => x,
    }
}

/// Whether the grammar knows `unit`.
pub fn is_known(unit: &str) -> bool {
    factor(unit).is_some()
}

/// `value` given in `from` expressed in the entity's unit `to` (a `uom` string): `None` when the
/// units measure different quantities or one is unknown and the two differ.
pub fn convert(value: f64, from: &str, to: &str) -> Option<f64> {
    let (from, to) = (normalise(from), normalise(to));
    if from == to {
        return Some(value);
    }
    let (qf, ff) = factor(from)?;
    let (qt, ft) = factor(to)?;
    (qf == qt).then(|| value * ff / ft)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn conversions() {
        assert_eq!(convert(1200.0, "cm", "m"), Some(12.0));
        assert_eq!(convert(1.5, "km", "urn:ogc:def:uom:UCUM::m"), Some(1500.0));
        assert_eq!(convert(10.0, "ft", "#m"), Some(3.048));
        assert_eq!(convert(1.0, "m", "m2"), None, "length vs area");
        assert_eq!(convert(2.0, "m", "storeys"), None);
        assert_eq!(convert(2.0, "storeys", "storeys"), Some(2.0));
        assert!((convert(180.0, "deg", "rad").unwrap() - std::f64::consts::PI).abs() < 1e-12);
        assert!(KNOWN.iter().all(|u| is_known(u)));
    }
}
