//! Objects cut by a tile border, joined into one instance by the merge (docs/tile.md, "The
//! merge").
//!
//! Each tile associates its own masks, so a car, tree or person whose Gaussians straddle a core
//! border becomes an image group in each tile. Both tiles hold the Gaussians of the region where
//! their core + margin boxes overlap (the shared margin) and both label them. The rule: groups `a`
//! of tile A and `b` of tile B are the same object when they have the same class and the
//! Gaussians that A labels `a` *and* B labels `b` number at least [`JOIN_FRACTION`] of each
//! group's Gaussians in the shared margin:
//!
//! `n(a, b) ≥ f · |a ∩ S_AB|` and `n(a, b) ≥ f · |b ∩ S_AB|`,
//!
//! `S_AB` the Gaussians both tiles hold. Requiring it of both groups (not of the smaller alone)
//! keeps a small fragment that lies inside another object's group from joining it. Joins are
//! closed transitively (a union–find), so an object cut by several borders becomes one instance;
//! its id is the smallest merged id of its groups (the group of the first tile in plan order), so
//! the result depends on neither the order tiles ran in nor the thread count. City labels are
//! unique by object id already and take no part.
use std::collections::{BTreeMap, HashMap};
use std::path::PathBuf;

use serde::{Deserialize, Serialize};

use super::TileError;

/// The fraction `f` of the join rule. Scored on eight SIMULATED `small` scenes with 8 trees, 10
/// cars and 16 persons cut by 8 and 9 m tiles (docs/tile.md, `scripts/score_tile_joins.py`):
/// the smallest fraction at which every class has the untiled run's instance count; below it
/// more groups of different objects join, above it more groups of one object stay apart.
pub const JOIN_FRACTION: f64 = 0.4;

/// One tile's label of a Gaussian that another tile holds too.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub struct Sighting {
    /// The Gaussian (its index in the scene's PLY).
    pub gaussian: u64,
    /// The tile (its index in the plan).
    pub tile: u32,
    /// Its merged image label (`Δ + offset + group`), or −1 (a city label, or none).
    pub group: i32,
}

/// Two groups of neighbouring tiles found to be one object.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Join {
    /// The tiles (indices in the plan, ascending).
    pub tiles: [u32; 2],
    /// Their merged image labels before the join.
    pub groups: [i32; 2],
    pub class: i32,
    /// Gaussians labelled `groups[0]` by the first tile and `groups[1]` by the second.
    pub shared: u64,
    /// Each group's Gaussians in the region both tiles hold.
    pub in_shared: [u64; 2],
}

/// The outcome of [`join`].
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Joined {
    /// Every joined group that is not its instance's id → the instance's id (the smallest id).
    pub root: HashMap<i32, i32>,
    /// The pairs that met the rule, by ascending groups.
    pub joins: Vec<Join>,
}

impl Joined {
    /// The instance id of merged label `id` (itself unless it was joined into another).
    pub fn id(&self, id: i32) -> i32 {
        self.root.get(&id).copied().unwrap_or(id)
    }
}

/// Applies the rule (module docs) with fraction `fraction` to the sightings (any order; a tile
/// seen twice for one Gaussian counts once). `class_of` gives a merged image label's class.
pub fn join(mut sightings: Vec<Sighting>, class_of: impl Fn(i32) -> i32, fraction: f64) -> Joined {
    sightings.sort_unstable();
    sightings.dedup_by_key(|s| (s.gaussian, s.tile));
    // Per pair of groups (first tile's, second tile's): their tiles and common Gaussians; per
    // (group, other tile): the group's Gaussians the other tile holds.
    let mut common: BTreeMap<(i32, i32), ([u32; 2], u64)> = BTreeMap::new();
    let mut in_shared: HashMap<(i32, u32), u64> = HashMap::new();
    for run in sightings.chunk_by(|x, y| x.gaussian == y.gaussian) {
        for (k, x) in run.iter().enumerate() {
            for y in &run[k + 1..] {
                if x.group >= 0 {
                    *in_shared.entry((x.group, y.tile)).or_default() += 1;
                }
                if y.group >= 0 {
                    *in_shared.entry((y.group, x.tile)).or_default() += 1;
                }
                if x.group >= 0 && y.group >= 0 {
                    common
                        .entry((x.group, y.group))
                        .or_insert(([x.tile, y.tile], 0))
                        .1 += 1;
                }
            }
        }
    }
    let mut parent: HashMap<i32, i32> = HashMap::new();
    fn find(parent: &mut HashMap<i32, i32>, x: i32) -> i32 {
        let mut r = x;
        while let Some(&p) = parent.get(&r).filter(|&&p| p != r) {
            r = p;
        }
        let mut c = x;
        while c != r {
            let next = parent[&c];
            parent.insert(c, r);
            c = next;
        }
        r
    }
    let mut joins = Vec::new();
    for (&(a, b), &(tiles, n)) in &common {
        let class = class_of(a);
        if class != class_of(b) {
            continue;
        }
        let sa = in_shared[&(a, tiles[1])];
        let sb = in_shared[&(b, tiles[0])];
        let need = |s: u64| n as f64 >= fraction * s as f64;
        if !(need(sa) && need(sb)) {
            continue;
        }
        let (ra, rb) = (find(&mut parent, a), find(&mut parent, b));
        if ra != rb {
            parent.insert(ra.max(rb), ra.min(rb));
        }
        joins.push(Join {
            tiles,
            groups: [a, b],
            class,
            shared: n,
            in_shared: [sa, sb],
        });
    }
    let ids: Vec<i32> = parent.keys().copied().collect();
    let mut root = HashMap::new();
    for g in ids {
        let r = find(&mut parent, g);
        if r != g {
            root.insert(g, r);
        }
    }
    Joined { root, joins }
}

/// One merged tile as the join reads it: its plan index, `source.npy` (original index, core
/// flag), the run's `gaussians.npy` (label, class) and its image labels → merged ids.
pub struct TileLabels<'a> {
    pub tile: u32,
    pub source: PathBuf,
    pub gaussians: PathBuf,
    pub image_ids: &'a HashMap<i32, i32>,
}

/// Reads the tiles' labels twice: first which Gaussians two or more tiles hold and one labels
/// with an image group (a byte per Gaussian of the scene's `n`), then their sightings — memory
/// in the Gaussians near image groups in margins, not in the scene.
pub fn sightings(n: usize, tiles: &[TileLabels]) -> Result<Vec<Sighting>, TileError> {
    const HOLDERS: u8 = 0x7f;
    const IMAGE: u8 = 0x80;
    let read = |t: &TileLabels| -> Result<(Vec<i64>, Vec<i32>), TileError> {
        let (sshape, source) = crate::npy::read::<i64>(&t.source)?;
        let (gshape, labels) = crate::npy::read::<i32>(&t.gaussians)?;
        if sshape.len() != 2 || gshape.len() != 2 || sshape[0] != gshape[0] {
            return Err(TileError::Invalid(format!(
                "{} has shape {sshape:?} but {} has {gshape:?}; the tile's run is not of its cut PLY",
                t.source.display(),
                t.gaussians.display()
            )));
        }
        for s in source.chunks_exact(2) {
            if usize::try_from(s[0]).map_or(true, |i| i >= n) {
                return Err(TileError::Invalid(format!(
                    "{}: index {} is outside the scene's {n} Gaussians",
                    t.source.display(),
                    s[0]
                )));
            }
        }
        Ok((source, labels))
    };
    let mut seen = vec![0u8; n];
    for t in tiles {
        let (source, labels) = read(t)?;
        for (s, g) in source.chunks_exact(2).zip(labels.chunks_exact(2)) {
            let b = &mut seen[s[0] as usize];
            *b = (*b & IMAGE) | ((*b & HOLDERS) + 1).min(HOLDERS);
            if t.image_ids.contains_key(&g[0]) {
                *b |= IMAGE;
            }
        }
    }
    let mut out = Vec::new();
    for t in tiles {
        let (source, labels) = read(t)?;
        for (s, g) in source.chunks_exact(2).zip(labels.chunks_exact(2)) {
            let b = seen[s[0] as usize];
            if b & IMAGE != 0 && b & HOLDERS >= 2 {
                out.push(Sighting {
                    gaussian: s[0] as u64,
                    tile: t.tile,
                    group: t.image_ids.get(&g[0]).copied().unwrap_or(-1),
                });
            }
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `count` Gaussians from `first` on, labelled `group` by `tile`.
    fn seen(out: &mut Vec<Sighting>, tile: u32, group: i32, first: u64, count: u64) {
        out.extend((first..first + count).map(|gaussian| Sighting {
            gaussian,
            tile,
            group,
        }));
    }

    #[test]
    fn groups_sharing_enough_of_both_their_margins_join_in_chains_of_one_class() {
        // Classes by id: 100–199 cars (class 8), 200–299 trees (class 6).
        let class = |id: i32| if id < 200 { 8 } else { 6 };
        let mut s = Vec::new();
        // A car cut by the border of tiles 0 and 1: Gaussians 0..100 lie in both tiles; tile 0
        // labels them 100, tile 1 labels 0..60 as 110 and 60..100 as −1 (a city label).
        // n = 60, |100 ∩ S| = 100, |110 ∩ S| = 60: 60 ≥ 0.4·100 and 60 ≥ 0.4·60 → joined.
        seen(&mut s, 0, 100, 0, 100);
        seen(&mut s, 1, 110, 0, 60);
        seen(&mut s, 1, -1, 60, 40);
        // The same car goes on into tile 2: Gaussians 1000..1050 in tiles 1 and 2.
        seen(&mut s, 1, 110, 1000, 50);
        seen(&mut s, 2, 120, 1000, 50);
        // A tree beside it, also in tiles 0 and 1, with the same Gaussians as a car group of
        // tile 1: another class, never joined.
        seen(&mut s, 0, 200, 2000, 80);
        seen(&mut s, 1, 130, 2000, 80);
        // A small group of tile 0 (20 Gaussians) wholly inside a large group of tile 1 (500 in
        // the shared margin): 20 ≥ 0.4·20 but 20 < 0.4·500 → apart.
        seen(&mut s, 0, 140, 3000, 20);
        seen(&mut s, 0, -1, 3020, 480);
        seen(&mut s, 1, 150, 3000, 500);
        // Two groups that share 39 of their 100 and 100 Gaussians in the shared margin: just
        // below 0.4 → apart; the same with 40 → joined (the threshold is inclusive).
        seen(&mut s, 0, 160, 4000, 100);
        seen(&mut s, 0, -1, 4100, 61);
        seen(&mut s, 1, -1, 4000, 61);
        seen(&mut s, 1, 170, 4061, 100);
        seen(&mut s, 0, 161, 5000, 100);
        seen(&mut s, 0, -1, 5100, 60);
        seen(&mut s, 1, -1, 5000, 60);
        seen(&mut s, 1, 171, 5060, 100);
        // The input order does not matter.
        let mut rev = s.clone();
        rev.reverse();
        let j = join(s, class, JOIN_FRACTION);
        assert_eq!(j, join(rev, class, JOIN_FRACTION));
        let mut root: Vec<(i32, i32)> = j.root.iter().map(|(&a, &b)| (a, b)).collect();
        root.sort_unstable();
        assert_eq!(root, vec![(110, 100), (120, 100), (171, 161)]);
        assert_eq!(j.id(120), 100);
        assert_eq!(j.id(200), 200);
        let pairs: Vec<([i32; 2], [u64; 3])> = j
            .joins
            .iter()
            .map(|x| (x.groups, [x.shared, x.in_shared[0], x.in_shared[1]]))
            .collect();
        assert_eq!(
            pairs,
            vec![
                ([100, 110], [60, 100, 60]),
                ([110, 120], [50, 50, 50]),
                ([161, 171], [40, 100, 100]),
            ]
        );
        assert_eq!(j.joins[1].tiles, [1, 2]);
        assert_eq!(j.joins[0].class, 8);
    }

    #[test]
    fn a_chain_takes_the_smallest_id_whatever_order_its_links_come_in() {
        let mut s = Vec::new();
        // 300 (tile 3) – 150 (tile 1) – 120 (tile 0) – 90 (tile 2), each link 10 Gaussians.
        seen(&mut s, 3, 300, 0, 10);
        seen(&mut s, 1, 150, 0, 10);
        seen(&mut s, 1, 150, 10, 10);
        seen(&mut s, 0, 120, 10, 10);
        seen(&mut s, 0, 120, 20, 10);
        seen(&mut s, 2, 90, 20, 10);
        let j = join(s, |_| 7, 1.0);
        let mut root: Vec<(i32, i32)> = j.root.into_iter().collect();
        root.sort_unstable();
        assert_eq!(root, vec![(120, 90), (150, 90), (300, 90)]);
    }
}
