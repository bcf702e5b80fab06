//! The hierarchy builder: city objects (class, parent, gml:id), their simple and generic
//! attributes, duplicate gml:ids, the ids derived for objects without one, and the LoD
//! chosen per building.
use std::collections::{BTreeMap, HashMap};

use super::model::*;
use super::reader::{Attrs, Parser, Tag};

pub(super) const SIMPLE_ATTRS: &[&str] = &[
    "measuredHeight",
    "function",
    "usage",
    "class",
    "roofType",
    "storeysAboveGround",
    "storeysBelowGround",
    "storeyHeightsAboveGround",
    "storeyHeightsBelowGround",
    "yearOfConstruction",
    "yearOfDemolition",
    "creationDate",
    "terminationDate",
    "relativeToTerrain",
    "relativeToWater",
    "name",
    "description",
];
pub(super) const CONTAINMENT: &[&str] = &[
    "boundedBy",
    "boundary",
    "opening",
    "outerBuildingInstallation",
    "buildingInstallation",
    "consistsOfBuildingPart",
    "buildingPart",
    "fillingSurface",
    "filling",
    "buildingConstructiveElement",
    "cityObjectMember",
    "featureMember",
];

pub(super) struct GenAttrBuilder {
    kind: String,
    name: Option<String>,
    value: Option<String>,
    uom: Option<String>,
}

impl Parser {
    /// A gml:id used a second time: a warning; a city object gets a unique name so the
    /// hierarchy table stays unambiguous.
    pub(super) fn duplicate_id(&mut self, id: &str, first: u64, line: u64, is_object: bool) {
        if !is_object {
            self.warn(
                line,
                Some(id.to_string()),
                format!("gml:id \"{id}\" is already used at line {first}; gml:ids must be unique in a file, so references to it are ambiguous"),
            );
            return;
        }
        let o = self.objects.len() - 1;
        let unique = super::unique_id(id, |c| self.ids.contains_key(c));
        self.ids.insert(unique.clone(), line);
        let class = self.objects[o].class.name();
        self.objects[o].object_id = unique.clone();
        self.warn(
            line,
            Some(id.to_string()),
            format!("gml:id \"{id}\" is already used at line {first}; this {class} is called \"{unique}\" in the hierarchy table"),
        );
    }

    pub(super) fn current_object(&self) -> Option<usize> {
        self.object_stack.last().copied()
    }

    /// A city object's start tag: the object, a child of the one open around it.
    pub(super) fn begin_object(&mut self, class: Class, a: &Attrs, line: u64) -> Tag {
        let parent = self.current_object();
        let idx = self.objects.len();
        self.objects.push(CityObject {
            class,
            object_id: a.gml_id.clone().unwrap_or_default(),
            has_gml_id: a.gml_id.is_some(),
            parent,
            attributes: BTreeMap::new(),
            line,
            offset: self.tag_offset,
            lod_used: None,
        });
        self.object_stack.push(idx);
        Tag::Object
    }

    /// A simple attribute of the object open around it (its `uom`, if any, is kept too).
    pub(super) fn attribute_start(&mut self, local: &str, a: &Attrs) -> Tag {
        self.begin_text();
        if let (Some(uom), Some(o)) = (&a.uom, self.current_object()) {
            self.objects[o]
                .attributes
                .insert(format!("{local}.uom"), uom.clone().into());
        }
        Tag::Attr(local.to_string())
    }

    pub(super) fn generic_start(&mut self, local: &str, a: &Attrs) -> Tag {
        match local {
            "genericAttributeSet" | "GenericAttributeSet" => {
                if let Some(n) = &a.name {
                    self.gen_set.push(n.clone());
                }
                Tag::Plain
            }
            "name" if !self.gen_attrs.is_empty() => {
                self.begin_text();
                Tag::GenName
            }
            "value" | "highReference" | "lowReference" | "status" if !self.gen_attrs.is_empty() => {
                if let Some(g) = self.gen_attrs.last_mut()
                    && a.uom.is_some()
                {
                    g.uom = a.uom.clone();
                }
                self.begin_text();
                if local == "value" {
                    Tag::GenValue
                } else {
                    Tag::Attr(format!("height.{local}"))
                }
            }
            _ if local.ends_with("Attribute") || local == "Height" => {
                let name = if local == "Height" {
                    Some("height".to_string())
                } else {
                    a.name.clone()
                };
                self.gen_attrs.push(GenAttrBuilder {
                    kind: local.to_string(),
                    name,
                    value: None,
                    uom: a.uom.clone(),
                });
                Tag::GenAttr
            }
            _ => Tag::Unknown,
        }
    }

    fn set_attr(&mut self, key: String, value: serde_json::Value) {
        let Some(o) = self.current_object() else {
            return;
        };
        let attrs = &mut self.objects[o].attributes;
        match attrs.get_mut(&key) {
            None => {
                attrs.insert(key, value);
            }
            Some(serde_json::Value::Array(v)) => v.push(value),
            Some(old) => {
                let prev = old.take();
                *old = serde_json::Value::Array(vec![prev, value]);
            }
        }
    }

    /// The end of a simple attribute: its text, typed, is set on the object.
    pub(super) fn finish_attr(&mut self, key: String) {
        let text = self.take_text();
        let text = text.trim();
        if !text.is_empty() {
            let value = typed_value(&key, text);
            self.set_attr(key, value);
        }
    }

    /// The end of a generic attribute's name.
    pub(super) fn finish_gen_name(&mut self) {
        let t = self.take_text();
        if let Some(g) = self.gen_attrs.last_mut() {
            g.name = Some(t.trim().to_string());
        }
    }

    /// The end of a generic attribute's value.
    pub(super) fn finish_gen_value(&mut self) {
        let t = self.take_text();
        if let Some(g) = self.gen_attrs.last_mut() {
            g.value = Some(t.trim().to_string());
        }
    }

    /// The end of a generic attribute: set on the object under its set-qualified name, typed
    /// by its kind, with its `uom` where it has one.
    pub(super) fn finish_generic_attribute(&mut self) {
        if let Some(g) = self.gen_attrs.pop()
            && let (Some(name), Some(value)) = (g.name, g.value)
        {
            let mut key = self
                .gen_set
                .iter()
                .map(|s| format!("{s}/"))
                .collect::<String>();
            key.push_str(&name);
            let kind = g.kind.to_ascii_lowercase();
            let v = if kind.starts_with("int") {
                value
                    .parse::<i64>()
                    .map(Into::into)
                    .unwrap_or_else(|_| value.clone().into())
            } else if kind.starts_with("double") || kind.starts_with("measure") || kind == "height"
            {
                value
                    .parse::<f64>()
                    .ok()
                    .and_then(serde_json::Number::from_f64)
                    .map(Into::into)
                    .unwrap_or_else(|| value.clone().into())
            } else {
                value.clone().into()
            };
            if let Some(uom) = g.uom {
                self.set_attr(format!("{key}.uom"), uom.into());
            }
            self.set_attr(key, v);
        }
    }

    /// Objects without gml:id get `<parent id>/<Class>[k]` (k counts siblings of that class
    /// in document order), or `<file stem>/<Class>[k]` at top level; made unique if needed.
    pub(super) fn derive_ids(&mut self) {
        let stem = self
            .path
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default();
        let mut taken: std::collections::HashSet<String> = self
            .objects
            .iter()
            .filter(|o| o.has_gml_id)
            .map(|o| o.object_id.clone())
            .collect();
        let mut sibling: HashMap<(Option<usize>, Class), usize> = HashMap::new();
        for i in 0..self.objects.len() {
            let (parent, class) = (self.objects[i].parent, self.objects[i].class);
            let k = sibling.entry((parent, class)).or_default();
            *k += 1;
            if self.objects[i].has_gml_id {
                continue;
            }
            let base = match parent {
                Some(p) => self.objects[p].object_id.clone(),
                None => stem.clone(),
            };
            let mut id = format!("{base}/{}[{}]", class.name(), *k);
            if taken.contains(&id) {
                id = super::unique_id(&id, |c| taken.contains(c));
            }
            taken.insert(id.clone());
            self.objects[i].object_id = id;
        }
    }

    /// Per top-level object (building): use LoD3 geometry; where the building has none,
    /// fall back to LoD2, then LoD1, and say so. LoD0 and LoD4 are never used.
    pub(super) fn choose_lods(&mut self) {
        let n = self.objects.len();
        let mut root = vec![0usize; n];
        for (i, o) in self.objects.iter().enumerate() {
            root[i] = match o.parent {
                Some(p) => root[p],
                None => i,
            };
        }
        let mut present: BTreeMap<usize, [bool; 5]> = BTreeMap::new();
        for poly in &self.polygons {
            if let (Some(o), Some(l)) = (poly.owner, poly.lod) {
                present.entry(root[o]).or_default()[l.min(4) as usize] = true;
            }
        }
        let mut chosen: BTreeMap<usize, u8> = BTreeMap::new();
        for (&r, lods) in &present {
            let pick = [3u8, 2, 1].into_iter().find(|&l| lods[l as usize]);
            if let Some(l) = pick {
                chosen.insert(r, l);
                if l != 3 {
                    let id = self.objects[r].object_id.clone();
                    let line = self.objects[r].line;
                    self.warn(line, Some(id), format!("no LoD3 geometry: using LoD{l}"));
                }
            } else {
                let id = self.objects[r].object_id.clone();
                let line = self.objects[r].line;
                self.warn(
                    line,
                    Some(id),
                    "no LoD1–3 geometry (only LoD0/LoD4): nothing to triangulate".into(),
                );
            }
        }
        for (o, r) in self.objects.iter_mut().zip(&root) {
            o.lod_used = chosen.get(r).copied();
        }
    }
}

/// Numbers stay numbers (measuredHeight, storeys, years); everything else is text.
fn typed_value(key: &str, text: &str) -> serde_json::Value {
    let numeric = matches!(
        key,
        "measuredHeight"
            | "storeysAboveGround"
            | "storeysBelowGround"
            | "yearOfConstruction"
            | "yearOfDemolition"
    );
    if numeric {
        if let Ok(i) = text.parse::<i64>() {
            return i.into();
        }
        if let Some(n) = text
            .parse::<f64>()
            .ok()
            .and_then(serde_json::Number::from_f64)
        {
            return n.into();
        }
    }
    text.to_string().into()
}
