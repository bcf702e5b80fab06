//! The PLY cut of a tile plan: one pass over the scene's PLY in chunks of rows
//! ([`crate::ply::FixedRows`]); each Gaussian's centre is taken back to the georeferenced ground
//! plane and its row is copied byte for byte into every tile whose core + margin holds it, with
//! its original index (and whether it lies in that tile's core) in the tile's `source.npy`.
//! Memory: one chunk, one bounded buffer per tile and a bounded visibility sample per tile —
//! independent of the PLY's size. Each output's header is written first at a fixed size and
//! rewritten in place at the end, when the row count is known.
use std::collections::BinaryHeap;
use std::io::{Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use glam::DVec3;

use super::{Grid, TileError};
use crate::alignment::Alignment;
use crate::ply::{self, ElementDef, FixedRows};

/// Rows decoded per chunk.
const CHUNK_ROWS: usize = 1 << 16;
/// All tiles' output buffers together hold at most this many bytes before they are flushed.
const BUFFER_BUDGET: usize = 256 << 20;
/// Bytes reserved for an output PLY header beyond the header without padding.
const PLY_HEADER_ROOM: usize = 64;
/// Bytes reserved for a `source.npy` header.
const NPY_HEADER: usize = 128;
/// Opacity (after the sigmoid) below which a Gaussian is not used to test which views see a tile.
const SAMPLE_MIN_OPACITY: f64 = 0.3;

/// What the cut found per tile.
#[derive(Debug, Clone, Default)]
pub struct TileCut {
    /// Gaussians written (core + margin).
    pub gaussians: usize,
    /// Of which in the tile's core.
    pub core: usize,
    /// An even sample of the opaque core Gaussians' centres (scene frame), for the view test.
    pub sample: Vec<DVec3>,
}

/// One output file written in appended chunks.
struct Output {
    path: PathBuf,
    buf: Vec<u8>,
}

impl Output {
    fn new(path: PathBuf, head: Vec<u8>) -> Result<Output, TileError> {
        std::fs::write(&path, &head).map_err(|err| TileError::Io {
            path: path.clone(),
            err,
        })?;
        Ok(Output {
            path,
            buf: Vec::new(),
        })
    }

    fn flush(&mut self) -> Result<(), TileError> {
        if self.buf.is_empty() {
            return Ok(());
        }
        let io = |err| TileError::Io {
            path: self.path.clone(),
            err,
        };
        let mut f = std::fs::OpenOptions::new()
            .append(true)
            .open(&self.path)
            .map_err(io)?;
        f.write_all(&self.buf).map_err(io)?;
        self.buf.clear();
        Ok(())
    }

    /// Rewrites the first bytes (the header, of unchanged length).
    fn rewrite_head(&mut self, head: &[u8]) -> Result<(), TileError> {
        self.flush()?;
        let io = |err| TileError::Io {
            path: self.path.clone(),
            err,
        };
        let mut f = std::fs::OpenOptions::new()
            .write(true)
            .open(&self.path)
            .map_err(io)?;
        f.seek(SeekFrom::Start(0)).map_err(io)?;
        f.write_all(head).map_err(io)?;
        Ok(())
    }
}

/// The header of a tile's PLY: the source's comments, `comment gs4city tile NAME`, the vertex
/// element with `count` rows, padded by a comment to exactly `len` bytes (`None`: the length
/// that fits any count).
fn ply_header(src: &FixedRows, name: &str, count: usize, len: Option<usize>) -> String {
    let mut comments: Vec<String> = src.header.comments.clone();
    comments.push(format!("gs4city tile {name}"));
    let def = ElementDef {
        count,
        ..src.def().clone()
    };
    let text = |comments: &[String], def: &ElementDef| {
        let c: Vec<&str> = comments.iter().map(String::as_str).collect();
        ply::header_text(src.header.encoding, &c, std::slice::from_ref(def))
    };
    let len = len.unwrap_or_else(|| {
        text(
            &comments,
            &ElementDef {
                count: usize::MAX,
                ..def.clone()
            },
        )
        .len()
            + PLY_HEADER_ROOM
    });
    let bare = text(&comments, &def).len();
    // `comment p` + dots + `\n` is 10 + dots bytes.
    let dots = len - bare - 10;
    comments.push(format!("p{}", ".".repeat(dots)));
    let h = text(&comments, &def);
    debug_assert_eq!(h.len(), len);
    h
}

/// Cuts `ply` into the tiles of `grid`: `tile_dirs[t]/scene/point_cloud.ply` and
/// `tile_dirs[t]/source.npy` (int64 N×2: original index, 1 where the Gaussian lies in the core).
pub fn cut(
    ply: &Path,
    al: &Alignment,
    grid: &Grid,
    tile_dirs: &[PathBuf],
    names: &[String],
    sample_per_tile: usize,
) -> Result<(Vec<TileCut>, usize), TileError> {
    let src = FixedRows::open(ply, "vertex")?;
    let prop = |n: &str| src.def().property(n);
    let (Some(px), Some(py), Some(pz)) = (prop("x"), prop("y"), prop("z")) else {
        return Err(TileError::Invalid(format!(
            "{}: the vertex element has no x, y, z properties",
            ply.display()
        )));
    };
    let opacity = prop("opacity");
    let n_tiles = grid.nx * grid.ny;
    let head_len = ply_header(&src, &names[0], 0, None).len();
    let mut plys = Vec::with_capacity(n_tiles);
    let mut idx = Vec::with_capacity(n_tiles);
    for (t, dir) in tile_dirs.iter().enumerate() {
        let head = ply_header(&src, &names[t], 0, Some(head_len));
        plys.push(Output::new(
            dir.join("scene/point_cloud.ply"),
            head.into_bytes(),
        )?);
        idx.push(Output::new(
            dir.join("source.npy"),
            crate::npy::header::<i64>(&[0, 2], NPY_HEADER),
        )?);
    }
    let flush_at = (BUFFER_BUDGET / n_tiles.max(1) / 2).clamp(64 << 10, 8 << 20);
    let mut cuts = vec![TileCut::default(); n_tiles];
    // Per tile the `sample_per_tile` core Gaussians of smallest hash: an even, deterministic sample.
    let mut heaps: Vec<BinaryHeap<(u64, usize)>> = vec![BinaryHeap::new(); n_tiles];
    let mut sample_pos: Vec<std::collections::HashMap<usize, DVec3>> =
        vec![Default::default(); n_tiles];
    let stride = src.stride;
    let bar = crate::progress::Bar::new("tile: cut", src.count() as u64, "Gaussians");
    let mut tiles = Vec::with_capacity(9);
    src.for_each_chunk(CHUNK_ROWS, |first, bytes| {
        for (k, row) in bytes.chunks_exact(stride).enumerate() {
            let i = first + k;
            let p = DVec3::new(src.value(row, px), src.value(row, py), src.value(row, pz));
            let g = al.unapply(p);
            let core = grid.core_of(g.x, g.y);
            tiles.clear();
            grid.tiles_within(g.x, g.y, &mut tiles);
            for &t in &tiles {
                let in_core = t == core;
                let c = &mut cuts[t];
                c.gaussians += 1;
                plys[t].buf.extend_from_slice(row);
                idx[t].buf.extend_from_slice(&(i as i64).to_le_bytes());
                idx[t]
                    .buf
                    .extend_from_slice(&i64::from(in_core).to_le_bytes());
                if plys[t].buf.len() >= flush_at {
                    plys[t].flush()?;
                    idx[t].flush()?;
                }
                if in_core {
                    c.core += 1;
                    let opaque = opacity.is_none_or(|o| {
                        crate::splat::sigmoid(src.value(row, o) as f32) as f64 >= SAMPLE_MIN_OPACITY
                    });
                    if opaque && p.is_finite() && sample_per_tile > 0 {
                        let h = crate::hash::splitmix64(i as u64);
                        let heap = &mut heaps[t];
                        if heap.len() < sample_per_tile {
                            heap.push((h, i));
                            sample_pos[t].insert(i, p);
                        } else if heap.peek().is_some_and(|&(top, _)| h < top) {
                            if let Some((_, gone)) = heap.pop() {
                                sample_pos[t].remove(&gone);
                            }
                            heap.push((h, i));
                            sample_pos[t].insert(i, p);
                        }
                    }
                }
            }
        }
        bar.inc((bytes.len() / stride) as u64);
        Ok::<(), TileError>(())
    })?;
    bar.finish();
    for t in 0..n_tiles {
        let head = ply_header(&src, &names[t], cuts[t].gaussians, Some(head_len));
        plys[t].rewrite_head(head.as_bytes())?;
        idx[t].rewrite_head(&crate::npy::header::<i64>(
            &[cuts[t].gaussians, 2],
            NPY_HEADER,
        ))?;
        let mut s: Vec<(usize, DVec3)> = sample_pos[t].drain().collect();
        s.sort_by_key(|(i, _)| *i);
        cuts[t].sample = s.into_iter().map(|(_, p)| p).collect();
    }
    Ok((cuts, src.count()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn padded_headers_have_one_length_and_parse() {
        let dir =
            crate::fsutil::test_temp_dir().join(format!("gs4city-cut-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("a.ply");
        let mut bytes =
            b"ply\nformat binary_little_endian 1.0\ncomment hi\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
                .to_vec();
        for v in [1f32, 2., 3., 4., 5., 6.] {
            bytes.extend_from_slice(&v.to_le_bytes());
        }
        std::fs::write(&p, &bytes).unwrap();
        let src = FixedRows::open(&p, "vertex").unwrap();
        let len = ply_header(&src, "t0", 0, None).len();
        for n in [0usize, 7, 123_456_789_012] {
            let h = ply_header(&src, "t0", n, Some(len));
            assert_eq!(h.len(), len);
            let mut file = h.clone().into_bytes();
            if n == 7 {
                file.extend(std::iter::repeat_n(0u8, 7 * 12));
                let hd = ply::Header::parse(&p, &file).unwrap();
                assert_eq!(hd.elements[0].count, 7);
                assert_eq!(hd.comments, vec!["hi", "gs4city tile t0", &hd.comments[2]]);
                assert_eq!(hd.len, len);
            }
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
