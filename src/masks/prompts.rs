//! Text prompts and per-mask image features: the prompt → class resolution, the two prompt sets
//! of the paper's disambiguation (`T_city` = prompts of building classes 0–5, `T_fore` = prompts
//! of classes 6–11; class −1, e.g. "the sky", is in neither), and the scores of one mask.
//!
//! A prompt's class comes from the prompts file's optional `classes` map; a prompt it does not
//! list is resolved from its text by [`class_from_text`] (a keyword table, first match wins).
use std::path::Path;

use serde::{Deserialize, Serialize};

use super::MasksError;
use crate::classes;
use crate::sam::Prompts;

/// Keyword table of [`class_from_text`], in match order: the first row with a word of the
/// prompt wins. Words match whole (lowercase, split at non-letters), also with a plural `s`/`es`.
/// Things are listed before stuff ("a street tree" is a tree, "a street lamp" an object, "a
/// window of a building" a window), building parts before the building itself.
pub const KEYWORDS: [(&[&str], i32); 13] = [
    (&["ground surface"], classes::GROUND_SURFACE),
    (
        &[
            "tree",
            "trees",
            "vegetation",
            "bush",
            "shrub",
            "hedge",
            "leaf",
            "leaves",
            "branch",
            "plant",
            "foliage",
        ],
        classes::TREE,
    ),
    (
        &[
            "person",
            "pedestrian",
            "people",
            "man",
            "men",
            "woman",
            "women",
            "human",
            "child",
            "children",
            "cyclist",
        ],
        classes::PERSON,
    ),
    (
        &[
            "car",
            "bus",
            "truck",
            "vehicle",
            "van",
            "automobile",
            "taxi",
            "motorcycle",
        ],
        classes::CAR,
    ),
    (
        &[
            "sign",
            "pole",
            "lamp",
            "streetlight",
            "bench",
            "bicycle",
            "bike",
            "hydrant",
            "fence",
            "bollard",
            "object",
        ],
        classes::OTHER,
    ),
    (&["window", "glass", "pane"], classes::WINDOW),
    (&["door", "entrance", "gate"], classes::DOOR),
    (&["roof", "rooftop"], classes::ROOF),
    (
        &["balcony", "chimney", "dormer", "installation", "awning"],
        classes::INSTALLATION,
    ),
    (
        &["wall", "facade", "façade", "building", "house"],
        classes::WALL,
    ),
    (
        &[
            "road", "street", "ground", "pavement", "sidewalk", "asphalt", "grass", "terrain",
            "lawn",
        ],
        classes::ROAD,
    ),
    (&["water", "river", "lake", "pond", "canal"], classes::WATER),
    (&["sky", "cloud", "clouds"], classes::NONE),
];

/// The class of a prompt from its text (the [`KEYWORDS`] table); `OTHER` (11, a foreground
/// object) when no keyword matches.
pub fn class_from_text(text: &str) -> i32 {
    let lower = text.to_lowercase();
    let words: Vec<&str> = lower
        .split(|c: char| !c.is_alphabetic())
        .filter(|w| !w.is_empty())
        .collect();
    let has = |kw: &str| -> bool {
        if kw.contains(' ') {
            let k: Vec<&str> = kw.split(' ').collect();
            return words.windows(k.len()).any(|w| w == k.as_slice());
        }
        words.iter().any(|w| {
            *w == kw || w.strip_suffix('s') == Some(kw) || w.strip_suffix("es") == Some(kw)
        })
    };
    for (kws, class) in KEYWORDS {
        if kws.iter().any(|k| has(k)) {
            return class;
        }
    }
    classes::OTHER
}

/// Which of the paper's prompt sets a class belongs to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PromptSet {
    /// `T_city`: classes 0–5.
    City,
    /// `T_fore`: classes 6–11.
    Fore,
    /// Class −1 (sky, unlabelled): in neither set; still a candidate of the class argmax.
    Neither,
}

impl PromptSet {
    pub fn of(class: i32) -> PromptSet {
        match class {
            0..=5 => PromptSet::City,
            6..=11 => PromptSet::Fore,
            _ => PromptSet::Neither,
        }
    }
}

/// How one prompt was resolved (written to `summary.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PromptInfo {
    pub text: String,
    pub class: i32,
    pub set: PromptSet,
    /// `"file"` (the prompts file's `classes`) or `"keyword"` ([`class_from_text`]).
    pub from: String,
}

/// The prompts, resolved and unit-normalised, ready for scoring.
#[derive(Debug, Clone)]
pub struct PromptTable {
    pub dim: usize,
    pub info: Vec<PromptInfo>,
    /// Unit vectors, `info.len() × dim`, row-major.
    unit: Vec<f32>,
}

/// The scores of one mask feature against the prompts.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FeatureScores {
    /// `S_city`: the best cosine over `T_city`.
    pub s_city: f64,
    /// `S_fore`: the best cosine over `T_fore`.
    pub s_fore: f64,
    /// Class of the best prompt overall (−1 for a sky-like prompt).
    pub class: i32,
    /// Best cosine minus the best cosine of a prompt of another class (0 with one class).
    pub margin: f64,
}

impl PromptTable {
    /// Resolves and checks a prompts file: `dim` > 0, every vector `dim` long, finite and
    /// non-zero, every class in −1..=11, and both sets non-empty.
    pub fn new(path: &Path, p: &Prompts) -> Result<PromptTable, MasksError> {
        let bad = |why: String| MasksError::Invalid {
            path: path.to_path_buf(),
            why,
        };
        if p.dim == 0 {
            return Err(bad("\"dim\" is 0".into()));
        }
        if p.prompts.is_empty() {
            return Err(bad("no prompts".into()));
        }
        if let Some(t) = p.classes.keys().find(|t| !p.prompts.contains_key(*t)) {
            return Err(bad(format!(
                "\"classes\" names prompt {t:?}, which \"prompts\" does not hold"
            )));
        }
        let mut info = Vec::with_capacity(p.prompts.len());
        let mut unit = Vec::with_capacity(p.prompts.len() * p.dim);
        for (text, v) in &p.prompts {
            if v.len() != p.dim {
                return Err(bad(format!(
                    "prompt {text:?} has {} values, \"dim\" is {}",
                    v.len(),
                    p.dim
                )));
            }
            let n = norm(v);
            if !n.is_finite() || n == 0.0 {
                return Err(bad(format!(
                    "prompt {text:?}: vector is zero or not finite"
                )));
            }
            let (class, from) = match p.classes.get(text) {
                Some(&c) => {
                    if !(classes::NONE..=classes::OTHER).contains(&c) {
                        return Err(bad(format!(
                            "prompt {text:?}: class {c} is outside -1..=11"
                        )));
                    }
                    (c, "file")
                }
                None => (class_from_text(text), "keyword"),
            };
            info.push(PromptInfo {
                text: text.clone(),
                class,
                set: PromptSet::of(class),
                from: from.into(),
            });
            unit.extend(v.iter().map(|&x| (x as f64 / n) as f32));
        }
        for (set, name) in [
            (PromptSet::City, "building (classes 0-5)"),
            (PromptSet::Fore, "foreground (classes 6-11)"),
        ] {
            if !info.iter().any(|i| i.set == set) {
                return Err(bad(format!(
                    "no {name} prompt: the disambiguation needs both sets (classes: {:?})",
                    info.iter().map(|i| (&i.text, i.class)).collect::<Vec<_>>()
                )));
            }
        }
        Ok(PromptTable {
            dim: p.dim,
            info,
            unit,
        })
    }

    /// Scores one feature row (any norm; a zero row scores 0 everywhere).
    pub fn score(&self, f: &[f32]) -> FeatureScores {
        debug_assert_eq!(f.len(), self.dim);
        let n = norm(f);
        let inv = if n > 0.0 { 1.0 / n } else { 0.0 };
        let mut s_city = f64::NEG_INFINITY;
        let mut s_fore = f64::NEG_INFINITY;
        let mut cos = Vec::with_capacity(self.info.len());
        for (i, info) in self.info.iter().enumerate() {
            let u = &self.unit[i * self.dim..(i + 1) * self.dim];
            let c = u
                .iter()
                .zip(f)
                .map(|(&a, &b)| a as f64 * b as f64)
                .sum::<f64>()
                * inv;
            match info.set {
                PromptSet::City => s_city = s_city.max(c),
                PromptSet::Fore => s_fore = s_fore.max(c),
                PromptSet::Neither => {}
            }
            cos.push(c);
        }
        // Best prompt (ties: the first in text order), then the best of another class.
        let mut best = 0;
        for (i, &c) in cos.iter().enumerate() {
            if c > cos[best] {
                best = i;
            }
        }
        let class = self.info[best].class;
        let other = cos
            .iter()
            .zip(&self.info)
            .filter(|(_, i)| i.class != class)
            .map(|(&c, _)| c)
            .fold(f64::NEG_INFINITY, f64::max);
        FeatureScores {
            s_city,
            s_fore,
            class,
            margin: if other.is_finite() {
                cos[best] - other
            } else {
                0.0
            },
        }
    }
}

fn norm(v: &[f32]) -> f64 {
    v.iter().map(|&x| x as f64 * x as f64).sum::<f64>().sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::BTreeMap;

    #[test]
    fn keyword_table_resolves_the_reference_prompts() {
        let cases = [
            ("a building", 0),
            ("a house", 0),
            ("a wall of a building", 0),
            ("a facade of a building", 0),
            ("a window of a building", 2),
            ("a door of a building", 3),
            ("a roof of a building", 1),
            ("a balcony of a building", 5),
            ("the ground surface of a building", 4),
            ("a tree", 6),
            ("a big tree", 6),
            ("a thin tree with branches", 6),
            ("vegetation", 6),
            ("bushes", 6),
            ("leaves and branches", 6),
            ("a street tree", 6),
            ("a tree with a building behind it", 6),
            ("a person", 7),
            ("people walking", 7),
            ("a pedestrian", 7),
            ("a car", 8),
            ("a bus", 8),
            ("a truck", 8),
            ("a traffic sign", 11),
            ("a pole", 11),
            ("a street lamp", 11),
            ("a road", 9),
            ("water", 10),
            ("the sky", -1),
            ("a teapot", 11),
        ];
        for (t, c) in cases {
            assert_eq!(class_from_text(t), c, "{t}");
        }
    }

    fn prompts(v: &[(&str, Vec<f32>)], classes: &[(&str, i32)]) -> Prompts {
        Prompts {
            simulated: false,
            dim: v[0].1.len(),
            prompts: v.iter().map(|(t, x)| (t.to_string(), x.clone())).collect(),
            classes: classes
                .iter()
                .map(|(t, c)| (t.to_string(), *c))
                .collect::<BTreeMap<_, _>>(),
        }
    }

    #[test]
    fn scores_are_cosines_over_the_two_sets_with_the_class_margin() {
        let p = prompts(
            &[
                ("a wall", vec![1.0, 0.0, 0.0]),
                ("a tree", vec![0.0, 2.0, 0.0]),
                ("the sky", vec![0.0, 0.0, 1.0]),
                ("thing x", vec![0.0, 1.0, 1.0]),
            ],
            &[("thing x", 8)],
        );
        let t = PromptTable::new(Path::new("p.json"), &p).unwrap();
        let car = t.info.iter().find(|i| i.text == "thing x").unwrap();
        assert_eq!(
            (car.class, car.set, car.from.as_str()),
            (8, PromptSet::Fore, "file")
        );
        // f = (3, 4, 0)/5: cos to wall 0.6, tree 0.8, sky 0, thing x 0.8/√2.
        let s = t.score(&[3.0, 4.0, 0.0]);
        assert!((s.s_city - 0.6).abs() < 1e-6);
        assert!((s.s_fore - 0.8).abs() < 1e-6);
        assert_eq!(s.class, 6);
        // Best other class: the wall (0.6 > 0.8/√2 of "thing x").
        assert!((s.margin - 0.2).abs() < 1e-6);
        // The sky prompt wins the class, but is in neither set.
        let s = t.score(&[0.0, 0.0, 5.0]);
        assert_eq!(s.class, -1);
        assert!((s.s_fore - 1.0 / 2f64.sqrt()).abs() < 1e-6);
        assert!(s.s_city.abs() < 1e-9);
    }

    #[test]
    fn bad_prompt_files_are_refused_naming_the_problem() {
        let e = |p: Prompts| {
            PromptTable::new(Path::new("p.json"), &p)
                .unwrap_err()
                .to_string()
        };
        let only_fore = prompts(&[("a tree", vec![1.0, 0.0])], &[]);
        assert!(e(only_fore).contains("no building"));
        let mut p = prompts(
            &[("a tree", vec![1.0, 0.0]), ("a roof", vec![0.0, 1.0])],
            &[],
        );
        p.prompts.insert("a car".into(), vec![1.0]);
        assert!(e(p).contains("\"a car\" has 1 values"));
        let p = prompts(
            &[("a tree", vec![1.0, 0.0]), ("a roof", vec![0.0, 1.0])],
            &[("a roof", 12)],
        );
        assert!(e(p).contains("outside"));
        let p = prompts(
            &[("a tree", vec![1.0, 0.0]), ("a roof", vec![0.0, 1.0])],
            &[("a boat", 8)],
        );
        assert!(e(p).contains("does not hold"));
        let p = prompts(
            &[("a tree", vec![1.0, 0.0]), ("a roof", vec![0.0, 0.0])],
            &[],
        );
        assert!(e(p).contains("zero"));
    }

    /// One-hot prompts of a semantic network's classes (`segment --semantic`) and mean class
    /// probabilities as features: `S_city` and `S_fore` are the best building and foreground
    /// class probabilities over the feature's norm, so a confident facade is decisively
    /// building, a confident hedge foreground, and a half-and-half mask within `δ = 0.05`.
    #[test]
    fn one_hot_prompts_score_class_probabilities() {
        let hot = |k: usize| {
            let mut v = vec![0.0f32; 4];
            v[k] = 1.0;
            v
        };
        let p = prompts(
            &[
                ("building", hot(0)),
                ("vegetation", hot(1)),
                ("road", hot(2)),
                ("sky", hot(3)),
            ],
            &[("building", 0), ("vegetation", 6), ("road", 9), ("sky", -1)],
        );
        let t = PromptTable::new(Path::new("p.json"), &p).unwrap();
        let facade = t.score(&[0.9, 0.05, 0.03, 0.02]);
        let n = (0.81f64 + 0.0025 + 0.0009 + 0.0004).sqrt();
        assert_eq!(facade.class, 0);
        assert!((facade.s_city - 0.9 / n).abs() < 1e-6 && (facade.s_fore - 0.05 / n).abs() < 1e-6);
        assert!(facade.s_city > facade.s_fore + 0.05);
        let hedge = t.score(&[0.1, 0.85, 0.03, 0.02]);
        assert!(hedge.class == 6 && hedge.s_fore > hedge.s_city + 0.05);
        let mixed = t.score(&[0.46, 0.44, 0.05, 0.05]);
        assert!((mixed.s_city - mixed.s_fore).abs() < 0.05, "{mixed:?}");
        assert_eq!(t.score(&[0.1, 0.1, 0.0, 0.8]).class, -1);
    }
}
