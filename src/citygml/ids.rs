//! Unique object ids: the one rule that names an object whose id is already taken (`id~2`,
//! `id~3`…), used for a gml:id repeated in one file, an id repeated across the features of a
//! CityJSONSeq, a derived id that meets a real one, and an id repeated across the files of a
//! city model ([`disambiguate`]).
use std::collections::{HashMap, HashSet};

use super::model::{CityModel, Warning};

/// `id~n` for the smallest `n ≥ 2` that `taken` does not hold.
pub fn unique_id(id: &str, taken: impl Fn(&str) -> bool) -> String {
    let mut n = 2u64;
    loop {
        let u = format!("{id}~{n}");
        if !taken(&u) {
            return u;
        }
        n += 1;
    }
}

/// Gives every object of the city model `models` (its files, in the order they are read) an id
/// of its own across the files: an object whose id an object of an earlier file already has
/// is a different object (a file reached twice is read once, before this) and is renamed
/// `id~n` by [`unique_id`]; the ids derived for objects without a gml:id below it
/// (`<parent id>/<Class>[k]`) follow their parent's new name. Returns one warning per renamed
/// object whose parent keeps its name, naming both files and the new name; a model without
/// ids repeated across files is left as it is and gives none.
pub fn disambiguate(models: &mut [CityModel]) -> Vec<Warning> {
    let mut taken: HashSet<String> = models
        .iter()
        .flat_map(|m| m.objects.iter().map(|o| o.object_id.clone()))
        .collect();
    // id → (file, line) of the object of an earlier file that has it.
    let mut first: HashMap<String, (usize, u64)> = HashMap::new();
    let mut warnings = Vec::new();
    for fi in 0..models.len() {
        let (before, rest) = models.split_at_mut(fi);
        let m = &mut rest[0];
        let mut renamed: Vec<Option<String>> = vec![None; m.objects.len()];
        for i in 0..m.objects.len() {
            let o = &m.objects[i];
            let mut id = o.object_id.clone();
            if !o.has_gml_id
                && let Some(p) = o.parent
                && let Some(new) = &renamed[p]
                && let Some(rest) = id.strip_prefix(m.objects[p].object_id.as_str())
                && rest.starts_with('/')
            {
                id = format!("{new}{rest}");
            }
            if let Some(&(ff, fl)) = first.get(&id) {
                let new = unique_id(&id, |c| taken.contains(c));
                if o.has_gml_id && o.parent.is_none_or(|p| renamed[p].is_none()) {
                    let below = count_below(m, i, |j| {
                        m.objects[j].has_gml_id && first.contains_key(&m.objects[j].object_id)
                    });
                    warnings.push(Warning {
                        file: m.path.display().to_string(),
                        line: o.line,
                        id: Some(id.clone()),
                        message: format!(
                            "this {} is also defined in {}:{fl}: the two objects are kept apart, \
                             and this one is called \"{new}\" in the hierarchy table{}",
                            o.class.name(),
                            before[ff].path.display(),
                            match below {
                                0 => String::new(),
                                n => format!(
                                    " (and {n} object(s) below it whose ids the other file uses \
                                     too are renamed the same way)"
                                ),
                            }
                        ),
                    });
                }
                id = new;
            }
            if id != m.objects[i].object_id {
                taken.insert(id.clone());
                renamed[i] = Some(id);
            }
        }
        for (o, new) in m.objects.iter_mut().zip(renamed) {
            if let Some(new) = new {
                o.object_id = new;
            }
        }
        for o in &m.objects {
            first.entry(o.object_id.clone()).or_insert((fi, o.line));
        }
    }
    warnings
}

/// The objects strictly below object `i` (its descendants) that satisfy `f`.
fn count_below(m: &CityModel, i: usize, f: impl Fn(usize) -> bool) -> usize {
    let mut inside = vec![false; m.objects.len()];
    inside[i] = true;
    let mut n = 0;
    for j in i + 1..m.objects.len() {
        if let Some(p) = m.objects[j].parent
            && inside[p]
        {
            inside[j] = true;
            n += usize::from(f(j));
        }
    }
    n
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::citygml::{CityObject, Class, ReadStats, Version};
    use std::collections::BTreeMap;

    fn obj(class: Class, id: &str, gml: bool, parent: Option<usize>) -> CityObject {
        CityObject {
            class,
            object_id: id.into(),
            has_gml_id: gml,
            parent,
            attributes: BTreeMap::new(),
            line: 1,
            offset: 0,
            lod_used: None,
        }
    }

    fn model(path: &str, objects: Vec<CityObject>) -> CityModel {
        CityModel {
            path: path.into(),
            version: Version::V2,
            srs_name: None,
            objects,
            polygons: Vec::new(),
            textures: Vec::new(),
            materials: Vec::new(),
            stats: ReadStats::default(),
            warnings: Vec::new(),
        }
    }

    #[test]
    fn the_next_free_suffix_is_taken() {
        let taken: HashSet<&str> = ["B~2", "B~3"].into_iter().collect();
        assert_eq!(unique_id("B", |c| taken.contains(c)), "B~4");
        assert_eq!(unique_id("C", |c| taken.contains(c)), "C~2");
    }

    #[test]
    fn an_id_of_an_earlier_file_renames_the_object_and_what_is_derived_below_it() {
        use Class::*;
        let mut ms = vec![
            model(
                "a.gml",
                vec![
                    obj(Building, "B", true, None),
                    obj(WallSurface, "W", true, Some(0)),
                    obj(RoofSurface, "B/RoofSurface[1]", false, Some(0)),
                ],
            ),
            model(
                "b.gml",
                vec![
                    obj(Building, "B", true, None),
                    obj(WallSurface, "W", true, Some(0)),
                    obj(RoofSurface, "B/RoofSurface[1]", false, Some(0)),
                    obj(Building, "C", true, None),
                    // A literal id that the renaming must step over.
                    obj(Building, "B~2", true, None),
                ],
            ),
            model("c.gml", vec![obj(Building, "B", true, None)]),
        ];
        let w = disambiguate(&mut ms);
        let ids = |m: &CityModel| -> Vec<String> {
            m.objects.iter().map(|o| o.object_id.clone()).collect()
        };
        assert_eq!(ids(&ms[0]), ["B", "W", "B/RoofSurface[1]"]);
        assert_eq!(
            ids(&ms[1]),
            ["B~3", "W~2", "B~3/RoofSurface[1]", "C", "B~2"]
        );
        assert_eq!(ids(&ms[2]), ["B~4"]);
        assert_eq!(w.len(), 2, "{w:?}");
        let text = w[0].to_string();
        assert!(
            text.starts_with("b.gml:1: B: this Building is also defined in a.gml:1")
                && text.contains("\"B~3\"")
                && text.contains("1 object(s) below it"),
            "{text}"
        );
        assert!(w[1].to_string().contains("\"B~4\""));
    }

    #[test]
    fn a_model_without_repeated_ids_is_left_as_it_is() {
        use Class::*;
        let mut ms = vec![
            model("a.gml", vec![obj(Building, "A", true, None)]),
            model("b.gml", vec![obj(Building, "B", true, None)]),
        ];
        assert!(disambiguate(&mut ms).is_empty());
        assert_eq!(ms[0].objects[0].object_id, "A");
        assert_eq!(ms[1].objects[0].object_id, "B");
    }
}
