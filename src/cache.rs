//! The contributions cache: per view, the per-pixel lists of `(Gaussian id, α·T)` of the
//! rasterizer (top-k by weight, in depth order, plus the dropped mass), the accumulated alpha and
//! the expected depth — rendered once, stored one file per view, and reused by every stage that
//! needs to know which Gaussians make a pixel (masks, associate, lift, train, query). Geometry is
//! frozen, so a rendered per-Gaussian quantity `x` at pixel `p` is exactly
//! `Σ_{i ∈ list(p)} w_i·x_i` (+ the truncated rest): forward passes are sparse products with
//! these lists and backward passes their transposes.
//!
//! File `<stem>.contrib` (little endian), version 4:
//! ```text
//! magic "GS4CCONT", u32 version = 4, u32 width, u32 height, u32 k (longest list; 0 = no bound),
//! u64 gaussians (ids are < this), u64 entries, u64 code bytes, u32 flags, 12 reserved → 64 bytes
//! u16 count[H·W]                           list length per pixel (row-major; ≤ 2344 by T_min)
//! u64 row_end[H]                           end of each image row's id code in the code bytes
//! u8 code[code bytes]                      the ids, pixel after pixel, each list in depth order
//! f16 weight[entries]                      the weights α·T, in the same order
//! f32 residual[H·W]                        α·T mass not kept (top-k or mass rule), 0 otherwise
//! f32 alpha[H·W]                           1 − T
//! f32 depth[H·W]                           expected depth Σw·z/(1−T); NaN where 1−T < 1e-3
//! f32 median[H·W]                          (flags bit 0) median depth of the kept lists
//! ```
//! The median depth is [`median_depth`] of the stored lists: the view-space z of the Gaussian
//! at which the kept weights first reach 0.5, NaN where they never do. The render stage stores
//! it so that the stages which need only the per-pixel planes (masks, openings) read the file's
//! tail ([`ViewPlanes`]) instead of decoding every list and loading the Gaussians' centres.
//! The id code is per image row (rows decode independently, in parallel): each id is one
//! LEB128 varint `v`; `v < n` (n = the length of the previous pixel's list in the row) means
//! "the previous pixel's `v`-th id" (neighbouring pixels share most of their Gaussians, so
//! most ids take one byte), otherwise `v − n` is the zigzag-coded difference to the last id
//! coded this way in the row (0 at the row's start). Versions 1 (u32 ids, f32 weights), 2
//! (u32 ids, f16 weights; both with the 24 reserved bytes and no row ends) and 3 (version 4
//! without the flags: no median plane) are still read.
//!
//! Weights are IEEE half floats (round to nearest even; relative error ≤ 2⁻¹¹, absolute
//! ≤ 3·10⁻⁸ below 2⁻¹⁴), with the error measured in BENCHMARKS.md. The list rule (top-k or
//! mass, `render::blend::ContributionMode`) is applied to the f32 weights before rounding,
//! and the renderer (`render::cache::contrib`) rounds them at once, so a view in memory
//! equals the view read back.
//!
//! A format: it imports no stage; the render stage builds the files (`render::cache`).
//!
//! Reading checks every size against the file length before allocating, the counts against `k`
//! and `entries`, ids against `gaussians`, and weights for finiteness.
use std::path::{Path, PathBuf};

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::camera::View;
use crate::fsutil;

const MAGIC: &[u8; 8] = b"GS4CCONT";
const VERSION: u32 = 4;
/// Bytes per stored weight of each readable version.
fn weight_bytes(version: u32) -> Option<usize> {
    match version {
        1 => Some(4),
        2..=4 => Some(2),
        _ => None,
    }
}
const HEADER: usize = 64;
/// Header flag (version 4): the file ends with the median-depth plane.
const FLAG_MEDIAN: u32 = 1;
/// Longest list a pixel can have: `(1 − 1/255)^n ≥ 1e-4` ⇒ `n ≤ 2344`.
pub const MAX_LIST: usize = 2344;

/// Writes `v` in little-endian byte order.
fn put<T: bytemuck::Pod + ToLe, W: std::io::Write>(w: &mut W, v: &[T]) -> std::io::Result<()> {
    if cfg!(target_endian = "little") {
        w.write_all(bytemuck::cast_slice(v))
    } else {
        v.iter()
            .try_for_each(|x| w.write_all(bytemuck::bytes_of(&x.to_le())))
    }
}

/// Reads little-endian values into `out`, reusing its memory (any alignment of `bytes`; its
/// length is a multiple of the size).
fn take_into<T: bytemuck::Pod + ToLe>(bytes: &[u8], out: &mut Vec<T>) {
    out.resize(bytes.len() / std::mem::size_of::<T>(), T::zeroed());
    bytemuck::cast_slice_mut::<T, u8>(out).copy_from_slice(bytes);
    if cfg!(target_endian = "big") {
        out.iter_mut().for_each(|x| *x = x.to_le());
    }
}

/// Byte order swap to/from little endian (its own inverse).
trait ToLe: Copy {
    fn to_le(self) -> Self;
}
impl ToLe for u16 {
    fn to_le(self) -> Self {
        u16::to_le(self)
    }
}
impl ToLe for u32 {
    fn to_le(self) -> Self {
        u32::to_le(self)
    }
}
impl ToLe for u64 {
    fn to_le(self) -> Self {
        u64::to_le(self)
    }
}
impl ToLe for half::f16 {
    fn to_le(self) -> Self {
        half::f16::from_bits(self.to_bits().to_le())
    }
}
impl ToLe for f32 {
    fn to_le(self) -> Self {
        f32::from_bits(self.to_bits().to_le())
    }
}

/// `depth` is NaN where the accumulated alpha is below this.
pub const DEPTH_MIN_ALPHA: f32 = 1e-3;

/// Per-pixel contribution lists in CSR form (row-major pixels).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Contributions {
    /// `offsets[p]..offsets[p + 1]` are pixel `p`'s entries; `H·W + 1` values.
    pub offsets: Vec<u64>,
    /// Gaussian indices, in depth order per pixel.
    pub ids: Vec<u32>,
    /// Weights `α·T`.
    pub weights: Vec<f32>,
    /// Per pixel, the weight mass not kept (top-k mode; zeros otherwise).
    pub residual: Vec<f32>,
}

impl Contributions {
    /// Pixel `p`'s `(ids, weights)`.
    pub fn pixel(&self, p: usize) -> (&[u32], &[f32]) {
        let (a, b) = (self.offsets[p] as usize, self.offsets[p + 1] as usize);
        (&self.ids[a..b], &self.weights[a..b])
    }
}

/// Errors of reading a cache file.
#[derive(Debug, thiserror::Error)]
pub enum CacheError {
    #[error("cannot read {path}: {err}")]
    Read { path: PathBuf, err: std::io::Error },
    #[error("{path}: not a gs4city contributions file: {why}")]
    Format { path: PathBuf, why: String },
    #[error("{path}: built for {found} Gaussians, the scene has {expected}: the cache is stale")]
    Stale {
        path: PathBuf,
        found: usize,
        expected: usize,
    },
    #[error(
        "{path}: {}×{} pixels (width × height), its view's camera is {}×{}",
        found.0, found.1, expected.0, expected.1
    )]
    Size {
        path: PathBuf,
        found: (usize, usize),
        expected: (usize, usize),
    },
    #[error(transparent)]
    Fs(#[from] fsutil::FsError),
}

/// One view's contributions (see the module docs).
#[derive(Debug, Clone, PartialEq)]
pub struct ViewContrib {
    pub width: usize,
    pub height: usize,
    /// List length bound (0 = complete lists).
    pub k: usize,
    /// Number of Gaussians of the scene the lists index.
    pub gaussians: usize,
    pub lists: Contributions,
    /// Accumulated alpha `1 − T` per pixel.
    pub alpha: Vec<f32>,
    /// Expected depth per pixel, NaN where the alpha is below `DEPTH_MIN_ALPHA`.
    pub depth: Vec<f32>,
    /// Median depth per pixel of the kept lists ([`median_depth`]); empty where not stored
    /// (files before version 4, views built without it).
    pub median: Vec<f32>,
}

impl ViewContrib {
    /// Pixel `p`'s `(ids, weights)`.
    #[inline]
    pub fn pixel(&self, p: usize) -> (&[u32], &[f32]) {
        self.lists.pixel(p)
    }

    /// Number of pixels.
    pub fn pixels(&self) -> usize {
        self.width * self.height
    }

    /// Number of `(id, weight)` entries.
    pub fn entries(&self) -> usize {
        self.lists.ids.len()
    }

    /// Bytes of the file this view is stored in (codes the ids to count them).
    pub fn file_bytes(&self) -> usize {
        let (code, ends) = encode_ids(self);
        HEADER
            + self.pixels() * (2 + 12)
            + ends.len() * 8
            + code.len()
            + self.entries() * 2
            + self.median.len() * 4
    }

    /// The header flags this view is written with.
    fn flags(&self) -> u32 {
        if self.median.is_empty() {
            0
        } else {
            FLAG_MEDIAN
        }
    }

    /// The file's bytes.
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut b = Vec::with_capacity(self.file_bytes());
        self.write_to(&mut b)
            .expect("writing to a Vec fails only for a median plane not of the pixel count");
        b
    }

    /// Streams the file's bytes into `w` (no copy of the whole file in memory); returns
    /// their number.
    pub fn write_to<W: std::io::Write>(&self, w: &mut W) -> std::io::Result<u64> {
        if !self.median.is_empty() && self.median.len() != self.pixels() {
            return Err(std::io::Error::other(format!(
                "{} median depths for {} pixels",
                self.median.len(),
                self.pixels()
            )));
        }
        let (code, ends) = encode_ids(self);
        let mut head = Vec::with_capacity(HEADER);
        head.extend_from_slice(MAGIC);
        for v in [
            VERSION,
            self.width as u32,
            self.height as u32,
            self.k as u32,
        ] {
            head.extend_from_slice(&v.to_le_bytes());
        }
        head.extend_from_slice(&(self.gaussians as u64).to_le_bytes());
        head.extend_from_slice(&(self.entries() as u64).to_le_bytes());
        head.extend_from_slice(&(code.len() as u64).to_le_bytes());
        head.extend_from_slice(&self.flags().to_le_bytes());
        head.resize(HEADER, 0);
        w.write_all(&head)?;
        // The counts and the half weights go out through small buffers, not as whole
        // arrays: no fresh memory per view on the writer thread.
        const CHUNK: usize = 4096;
        let mut counts = [0u16; CHUNK];
        let off = &self.lists.offsets;
        for start in (0..self.pixels()).step_by(CHUNK) {
            let n = CHUNK.min(self.pixels() - start);
            for (i, c) in counts[..n].iter_mut().enumerate() {
                *c = (off[start + i + 1] - off[start + i]) as u16;
            }
            put(w, &counts[..n])?;
        }
        put(w, &ends)?;
        w.write_all(&code)?;
        let mut halves = [half::f16::ZERO; CHUNK];
        for ws in self.lists.weights.chunks(CHUNK) {
            let h = &mut halves[..ws.len()];
            half::slice::HalfFloatSliceExt::convert_from_f32_slice(h, ws);
            put(w, h)?;
        }
        for arr in [&self.lists.residual, &self.alpha, &self.depth, &self.median] {
            put(w, arr)?;
        }
        Ok(
            (HEADER + 2 * self.pixels() + 8 * ends.len() + code.len() + 2 * self.entries()) as u64
                + (12 * self.pixels() + 4 * self.median.len()) as u64,
        )
    }

    /// Writes the view atomically; returns the file's size in bytes.
    pub fn write(&self, path: &Path) -> Result<u64, CacheError> {
        let mut bytes = 0;
        fsutil::atomic_write(path, |w| {
            bytes = self.write_to(w).map_err(|err| {
                CacheError::Fs(fsutil::FsError::Write {
                    path: path.to_path_buf(),
                    err,
                })
            })?;
            Ok::<(), CacheError>(())
        })?;
        Ok(bytes)
    }

    /// An empty view (0×0), to be filled by [`ViewContrib::read_into`].
    pub fn empty() -> Self {
        ViewContrib {
            width: 0,
            height: 0,
            k: 0,
            gaussians: 0,
            lists: Contributions::default(),
            alpha: Vec::new(),
            depth: Vec::new(),
            median: Vec::new(),
        }
    }

    /// Reads and checks a file; `expect_gaussians` (when given) must equal the stored count.
    pub fn read(path: &Path, expect_gaussians: Option<usize>) -> Result<Self, CacheError> {
        let mut v = Self::empty();
        v.read_into(path, expect_gaussians, &mut Vec::new())?;
        Ok(v)
    }

    /// [`ViewContrib::read`] into `self`, reusing its vectors and the file buffer `buf`: a stage
    /// that reads view after view allocates (and page-faults) once instead of per view. On an
    /// error `self` holds unspecified content.
    pub fn read_into(
        &mut self,
        path: &Path,
        expect_gaussians: Option<usize>,
        buf: &mut Vec<u8>,
    ) -> Result<(), CacheError> {
        use std::io::Read;
        let err = |err| CacheError::Read {
            path: path.to_path_buf(),
            err,
        };
        buf.clear();
        std::fs::File::open(path)
            .and_then(|mut f| f.read_to_end(buf))
            .map_err(err)?;
        self.parse_into(path, buf)?;
        check_count(path, self.gaussians, expect_gaussians)
    }

    /// Parses and checks a file's bytes (`path` names it in errors).
    pub fn from_bytes(path: &Path, b: &[u8]) -> Result<Self, CacheError> {
        let mut v = Self::empty();
        v.parse_into(path, b)?;
        Ok(v)
    }

    /// Parses and checks a file's bytes into `self`, reusing its vectors.
    fn parse_into(&mut self, path: &Path, b: &[u8]) -> Result<(), CacheError> {
        let bad = |why: String| CacheError::Format {
            path: path.to_path_buf(),
            why,
        };
        let hd = Header::parse(path, b, b.len() as u64)?;
        let Header {
            width,
            height,
            k,
            gaussians,
            entries,
            code_bytes,
            flags,
            ..
        } = hd;
        let (wb, coded, npx) = (hd.weight_bytes(), hd.coded(), hd.pixels());
        let mut o = HEADER;
        let bound = if k == 0 { MAX_LIST } else { k };
        let offsets = &mut self.lists.offsets;
        offsets.clear();
        offsets.reserve(npx + 1);
        offsets.push(0u64);
        for (p, c) in b[o..o + 2 * npx].chunks_exact(2).enumerate() {
            let n = usize::from(u16::from_le_bytes([c[0], c[1]]));
            if n > bound {
                return Err(bad(format!("pixel {p} has {n} entries, more than {bound}")));
            }
            offsets.push(offsets[p] + n as u64);
        }
        o += 2 * npx;
        if offsets[npx] != entries as u64 {
            return Err(bad(format!(
                "the per-pixel counts sum to {}, the header says {entries}",
                offsets[npx]
            )));
        }
        let ids = &mut self.lists.ids;
        if coded {
            let ends = &b[o..o + 8 * height];
            o += 8 * height;
            let code = &b[o..o + code_bytes];
            o += code_bytes;
            ids.resize(entries, 0);
            decode_ids(code, ends, offsets, width, gaussians as u64, ids).map_err(bad)?;
        } else {
            take_into(&b[o..o + 4 * entries], ids);
            if let Some(id) = ids.iter().find(|&&id| u64::from(id) >= gaussians as u64) {
                return Err(bad(format!(
                    "Gaussian id {id} is not below the Gaussian count {gaussians}"
                )));
            }
            o += 4 * entries;
        }
        let weights = &mut self.lists.weights;
        if wb == 4 {
            take_into(&b[o..o + 4 * entries], weights);
        } else {
            // Through a small buffer: no second entries-long allocation.
            weights.resize(entries, 0.0);
            let mut halves = [half::f16::ZERO; 4096];
            for (src, dst) in b[o..o + 2 * entries]
                .chunks(2 * halves.len())
                .zip(weights.chunks_mut(halves.len()))
            {
                let h = &mut halves[..dst.len()];
                bytemuck::cast_slice_mut::<half::f16, u8>(h).copy_from_slice(src);
                if cfg!(target_endian = "big") {
                    h.iter_mut().for_each(|x| *x = x.to_le());
                }
                half::slice::HalfFloatSliceExt::convert_to_f32_slice(&h[..], dst);
            }
        }
        o += wb * entries;
        for v in [&mut self.lists.residual, &mut self.alpha, &mut self.depth] {
            take_into(&b[o..o + 4 * npx], v);
            o += 4 * npx;
        }
        if flags & FLAG_MEDIAN != 0 {
            take_into(&b[o..o + 4 * npx], &mut self.median);
        } else {
            self.median.clear();
        }
        if let Some(i) = outside_unit(&self.lists.weights) {
            return Err(bad(format!("weight {i} is {}", self.lists.weights[i])));
        }
        if let Some(p) = [&self.lists.residual, &self.alpha]
            .into_iter()
            .filter_map(|v| outside_unit(v))
            .min()
        {
            return Err(bad(format!("pixel {p}: residual or alpha outside [0, 1]")));
        }
        self.width = width;
        self.height = height;
        self.k = k;
        self.gaussians = gaussians;
        Ok(())
    }
}

/// A stale cache: the file's Gaussian count `found` is not the expected one.
fn check_count(path: &Path, found: usize, expected: Option<usize>) -> Result<(), CacheError> {
    match expected {
        Some(n) if n != found => Err(CacheError::Stale {
            path: path.to_path_buf(),
            found,
            expected: n,
        }),
        _ => Ok(()),
    }
}

/// A file's checked header: every size it implies is checked against the file's length
/// before anything is allocated.
#[derive(Debug, Clone, Copy)]
struct Header {
    version: u32,
    width: usize,
    height: usize,
    k: usize,
    gaussians: usize,
    entries: usize,
    code_bytes: usize,
    flags: u32,
}

impl Header {
    /// Parses the header at the start of `b` (at least its first 64 bytes) of a file of
    /// `len` bytes.
    fn parse(path: &Path, b: &[u8], len: u64) -> Result<Header, CacheError> {
        let bad = |why: String| CacheError::Format {
            path: path.to_path_buf(),
            why,
        };
        if b.len() < HEADER || &b[..8] != MAGIC {
            return Err(bad("missing the GS4CCONT header".into()));
        }
        let u32_at = |o: usize| u32::from_le_bytes(b[o..o + 4].try_into().expect("4 bytes"));
        let u64_at = |o: usize| u64::from_le_bytes(b[o..o + 8].try_into().expect("8 bytes"));
        let version = u32_at(8);
        let wb = weight_bytes(version).ok_or_else(|| {
            bad(format!(
                "version {version}, this program reads 1 to {VERSION}"
            ))
        })? as u64;
        let (width, height, k) = (
            u32_at(12) as usize,
            u32_at(16) as usize,
            u32_at(20) as usize,
        );
        let (gaussians, entries) = (u64_at(24), u64_at(32));
        // Versions 3 and 4 code the ids (row ends + code bytes); 1 and 2 store them as u32.
        let coded = version >= 3;
        let code_bytes = if coded { u64_at(40) } else { 0 };
        let flags = if version >= 4 { u32_at(48) } else { 0 };
        if flags & !FLAG_MEDIAN != 0 {
            return Err(bad(format!("unknown header flags {flags:#x}")));
        }
        let npx = (width as u64)
            .checked_mul(height as u64)
            .filter(|&n| n > 0 && n <= 1 << 31)
            .ok_or_else(|| bad(format!("image size {width}×{height} is empty or too large")))?;
        let id_part = if coded {
            (height as u64 * 8).checked_add(code_bytes)
        } else {
            entries.checked_mul(4)
        };
        let planes = if flags & FLAG_MEDIAN != 0 { 18 } else { 14 };
        let expected = (HEADER as u64)
            .checked_add(npx * planes)
            .and_then(|x| id_part.and_then(|i| x.checked_add(i)))
            .and_then(|x| entries.checked_mul(wb).and_then(|e| x.checked_add(e)));
        if expected != Some(len) {
            return Err(bad(format!(
                "{len} bytes, the header ({width}×{height}, {entries} entries) needs {}",
                expected.map_or("more than 2^64".to_string(), |e| e.to_string())
            )));
        }
        if k > MAX_LIST || gaussians > u64::from(u32::MAX) + 1 {
            return Err(bad(format!(
                "k = {k} or {gaussians} Gaussians out of range"
            )));
        }
        // All sizes are below the file's length now, so they fit a usize.
        Ok(Header {
            version,
            width,
            height,
            k,
            gaussians: gaussians as usize,
            entries: entries as usize,
            code_bytes: code_bytes as usize,
            flags,
        })
    }

    fn weight_bytes(&self) -> usize {
        weight_bytes(self.version).expect("checked in parse")
    }

    fn coded(&self) -> bool {
        self.version >= 3
    }

    fn pixels(&self) -> usize {
        self.width * self.height
    }

    /// Bytes of the per-pixel planes at the file's end (residual, alpha, depth, median).
    fn planes_bytes(&self) -> usize {
        let planes = if self.flags & FLAG_MEDIAN != 0 { 4 } else { 3 };
        planes * 4 * self.pixels()
    }
}

/// The per-pixel planes of a cached view, without its lists ([`ViewPlanes::read`]).
#[derive(Debug, Clone, PartialEq)]
pub struct ViewPlanes {
    pub width: usize,
    pub height: usize,
    /// Accumulated alpha `1 − T`.
    pub alpha: Vec<f32>,
    /// Expected depth, NaN where the alpha is below `DEPTH_MIN_ALPHA`.
    pub depth: Vec<f32>,
    /// Median depth of the kept lists; `None` in files that do not store it (before version 4).
    pub median: Option<Vec<f32>>,
}

impl ViewPlanes {
    /// Reads only the header and the planes at the end of a cache file (the lists are
    /// skipped, not decoded); checks the header as a full read does, the stored Gaussian
    /// count against `expect_gaussians`, and the alpha's range.
    pub fn read(path: &Path, expect_gaussians: Option<usize>) -> Result<ViewPlanes, CacheError> {
        use std::io::{Read, Seek, SeekFrom};
        let err = |err| CacheError::Read {
            path: path.to_path_buf(),
            err,
        };
        let mut f = std::fs::File::open(path).map_err(err)?;
        let len = f.metadata().map_err(err)?.len();
        let mut head = Vec::with_capacity(HEADER);
        (&mut f)
            .take(HEADER as u64)
            .read_to_end(&mut head)
            .map_err(err)?;
        let hd = Header::parse(path, &head, len)?;
        check_count(path, hd.gaussians, expect_gaussians)?;
        let npx = hd.pixels();
        // The residual plane is skipped too: its readers read the lists.
        let skip = hd.planes_bytes() - 4 * npx;
        f.seek(SeekFrom::Start(len - skip as u64)).map_err(err)?;
        let mut b = vec![0u8; skip];
        f.read_exact(&mut b).map_err(err)?;
        let plane = |i: usize| {
            let mut v = Vec::new();
            take_into(&b[i * 4 * npx..(i + 1) * 4 * npx], &mut v);
            v
        };
        let (alpha, depth) = (plane(0), plane(1));
        let median = (hd.flags & FLAG_MEDIAN != 0).then(|| plane(2));
        if let Some(p) = outside_unit(&alpha) {
            return Err(CacheError::Format {
                path: path.to_path_buf(),
                why: format!("pixel {p}: alpha outside [0, 1]"),
            });
        }
        Ok(ViewPlanes {
            width: hd.width,
            height: hd.height,
            alpha,
            depth,
            median,
        })
    }
}

/// The first value of `v` outside `[0, 1 + 10⁻⁵]` (NaN and ±∞ included: they fail both
/// comparisons). Checked a block at a time without branching, so the compiler vectorises it.
fn outside_unit(v: &[f32]) -> Option<usize> {
    const BLOCK: usize = 1024;
    let inside = |x: f32| (0.0..=1.0 + 1e-5).contains(&x);
    v.chunks(BLOCK).enumerate().find_map(|(b, c)| {
        let all = c.iter().fold(true, |ok, &x| ok & inside(x));
        (!all).then(|| b * BLOCK + c.iter().position(|&x| !inside(x)).unwrap_or(0))
    })
}

/// Appends `v` as an LEB128 varint.
fn put_varint(out: &mut Vec<u8>, mut v: u64) {
    while v >= 0x80 {
        out.push((v as u8) | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}

/// Reads an LEB128 varint of at most 64 bits at `*pos`.
fn get_varint(b: &[u8], pos: &mut usize) -> Option<u64> {
    let mut v = 0u64;
    for shift in (0..64).step_by(7) {
        let byte = *b.get(*pos)?;
        *pos += 1;
        v |= u64::from(byte & 0x7f) << shift;
        if byte < 0x80 {
            return Some(v);
        }
    }
    None
}

/// The version 3 id code of `v` (see the module docs): the code bytes and, per image row,
/// the end of its code.
fn encode_ids(v: &ViewContrib) -> (Vec<u8>, Vec<u64>) {
    let ids = &v.lists.ids;
    let off = &v.lists.offsets;
    let mut code = Vec::with_capacity(ids.len() * 2);
    let mut ends = Vec::with_capacity(v.height);
    for y in 0..v.height {
        let mut prev: &[u32] = &[];
        let mut base = 0i64;
        for p in y * v.width..(y + 1) * v.width {
            let list = &ids[off[p] as usize..off[p + 1] as usize];
            // Neighbouring lists mostly hold the same Gaussians in the same order: the entry
            // after the last one found is tried first (any index of the id is a valid code;
            // the renderer's lists never repeat an id).
            let mut next = 0usize;
            for &id in list {
                let found = if prev.get(next) == Some(&id) {
                    Some(next)
                } else {
                    prev.iter().position(|&q| q == id)
                };
                if let Some(j) = found {
                    next = j + 1;
                }
                match found {
                    Some(j) => put_varint(&mut code, j as u64),
                    None => {
                        let d = i64::from(id) - base;
                        let zz = ((d << 1) ^ (d >> 63)) as u64;
                        put_varint(&mut code, prev.len() as u64 + zz);
                        base = i64::from(id);
                    }
                }
            }
            prev = list;
        }
        ends.push(code.len() as u64);
    }
    (code, ends)
}

/// Decodes the version 3 id code into `ids` (sized to the entries), one image row per task;
/// an error names the first bad row or pixel.
fn decode_ids(
    code: &[u8],
    ends: &[u8],
    offsets: &[u64],
    width: usize,
    gaussians: u64,
    ids: &mut [u32],
) -> Result<(), String> {
    let height = ends.len() / 8;
    let end_at = |y: usize| u64::from_le_bytes(ends[8 * y..8 * y + 8].try_into().expect("8 bytes"));
    let mut rows = Vec::with_capacity(height);
    let (mut rest, mut start) = (ids, 0u64);
    for y in 0..height {
        let end = end_at(y);
        if end < start || end > code.len() as u64 {
            return Err(format!(
                "row {y}: its id code ends at byte {end}, outside [{start}, {}]",
                code.len()
            ));
        }
        let n = (offsets[(y + 1) * width] - offsets[y * width]) as usize;
        let (mine, more) = rest.split_at_mut(n);
        rows.push((y, &code[start as usize..end as usize], mine));
        rest = more;
        start = end;
    }
    if start != code.len() as u64 {
        return Err(format!(
            "the rows' id code ends at byte {start} of {}",
            code.len()
        ));
    }
    let results: Vec<Result<(), String>> = rows
        .into_par_iter()
        .with_min_len(8)
        .map(|(y, row, out)| {
            let (mut pos, mut e, mut base) = (0usize, 0usize, 0i64);
            let (mut prev_start, mut prev_len) = (0usize, 0usize);
            for x in 0..width {
                let p = y * width + x;
                let n = (offsets[p + 1] - offsets[p]) as usize;
                for _ in 0..n {
                    // One-byte codes (most of them) without the general loop.
                    let v = match row.get(pos) {
                        Some(&b) if b < 0x80 => {
                            pos += 1;
                            u64::from(b)
                        }
                        _ => get_varint(row, &mut pos).ok_or_else(|| {
                            format!("pixel {p}: the id code ends early or overflows")
                        })?,
                    };
                    out[e] = if v < prev_len as u64 {
                        out[prev_start + v as usize]
                    } else {
                        let zz = v - prev_len as u64;
                        let d = (zz >> 1) as i64 ^ -((zz & 1) as i64);
                        let id = base
                            .checked_add(d)
                            .filter(|&id| id >= 0 && (id as u64) < gaussians);
                        let id = id.ok_or_else(|| {
                            format!(
                                "pixel {p}: a Gaussian id not below the Gaussian count {gaussians}"
                            )
                        })?;
                        base = id;
                        id as u32
                    };
                    e += 1;
                }
                (prev_start, prev_len) = (e - n, n);
            }
            if pos != row.len() {
                return Err(format!(
                    "row {y}: {} bytes of id code left over",
                    row.len() - pos
                ));
            }
            Ok(())
        })
        .collect();
    results.into_iter().collect()
}

/// Rounds weights to the stored precision (IEEE half, nearest even).
pub fn round_weights(w: &mut [f32]) {
    let h: Vec<half::f16> = half::vec::HalfFloatVecExt::from_f32_slice(w);
    half::slice::HalfFloatSliceExt::convert_to_f32_slice(&h[..], w);
}

/// Options of the cache: which contributions a pixel's list keeps.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct CacheOptions {
    /// Longest list per pixel (0 = no bound). With `epsilon = 0` the `top_k` largest weights.
    pub top_k: usize,
    /// The mass rule: a pixel keeps its largest weights until they reach `1 − epsilon` of its
    /// α·T mass (at most `top_k`); 0 = off (top-k lists). Absent in caches before version 3.
    #[serde(default)]
    pub epsilon: f32,
    /// Early stop: a pixel stops blending once its transmittance T falls below this after a
    /// contribution, so the Gaussians behind it (together at most `t_stop` of the pixel's
    /// mass) are neither listed nor counted in `residual`, `alpha` or `depth`. 0 (and in
    /// caches before it existed) = the rasterizer's own stop only (T < 10⁻⁴, before adding).
    #[serde(default)]
    pub t_stop: f32,
    /// The smallest α a Gaussian contributes with at a pixel: the rasterizer's own
    /// [`INRIA_ALPHA_MIN`] (and in caches before it existed), or higher, so that the faint
    /// tails of Gaussians are neither listed nor blended (nor counted in `residual`, `alpha`,
    /// `depth`).
    #[serde(default = "inria_alpha_min")]
    pub alpha_min: f32,
}

/// The smallest α INRIA's rasterizer blends (1/255).
pub const INRIA_ALPHA_MIN: f32 = 1.0 / 255.0;

fn inria_alpha_min() -> f32 {
    INRIA_ALPHA_MIN
}

/// The cache's default mass share ε (BENCHMARKS.md's git history, "Adaptive contribution lists").
pub const EPSILON: f32 = 0.05;
/// The cache's default early stop (BENCHMARKS.md's git history, "Early stop of the cache's blend").
pub const T_STOP: f32 = 0.02;
/// The cache's default bound on a list's length.
pub const TOP_K: usize = 32;

impl Default for CacheOptions {
    fn default() -> Self {
        CacheOptions {
            top_k: TOP_K,
            epsilon: EPSILON,
            t_stop: T_STOP,
            alpha_min: INRIA_ALPHA_MIN,
        }
    }
}

impl CacheOptions {
    /// Checks the options (the wording of [`crate::check::range`]): `top_k` at most
    /// [`MAX_LIST`], `epsilon` and `t_stop` in `[0, 1)`, `alpha_min` in
    /// `[`[`INRIA_ALPHA_MIN`]`, 0.99)`.
    pub fn validate(&self) -> Result<(), crate::check::OutOfRange> {
        use crate::check::{End, range};
        range(
            "top_k",
            self.top_k,
            End::Closed(0.0),
            End::Closed(MAX_LIST as f64),
        )?;
        range("epsilon", self.epsilon, End::Closed(0.0), End::Open(1.0))?;
        range("t_stop", self.t_stop, End::Closed(0.0), End::Open(1.0))?;
        range(
            "alpha_min",
            self.alpha_min,
            End::Closed(f64::from(INRIA_ALPHA_MIN)),
            End::Open(0.99),
        )
    }

    /// Today's lists in words, e.g. "top-16 lists" or "lists to 1 − 0.05 of the mass (≤ 32)".
    pub fn describe(&self) -> String {
        let lists = match (self.epsilon > 0.0, self.top_k) {
            (false, 0) => "complete lists".into(),
            (false, k) => format!("top-{k} lists"),
            (true, 0) => format!("lists to 1 − {} of the mass", self.epsilon),
            (true, k) => format!("lists to 1 − {} of the mass (≤ {k})", self.epsilon),
        };
        let lists = if self.t_stop > 0.0 {
            format!("{lists}, blending stopped at T < {}", self.t_stop)
        } else {
            lists
        };
        if self.alpha_min > INRIA_ALPHA_MIN {
            format!("{lists}, α ≥ {}", self.alpha_min)
        } else {
            lists
        }
    }
}

/// One cached view in [`CacheSummary`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CachedView {
    pub name: String,
    pub stem: String,
    pub width: usize,
    pub height: usize,
    pub entries: u64,
    /// Mean list length over pixels.
    pub mean_list: f64,
    /// Mean over covered pixels (alpha ≥ 1e-3) of the dropped mass `residual / alpha`.
    pub mean_dropped_share: f64,
    /// Fraction of pixels with alpha ≥ 1e-3.
    pub coverage: f64,
    pub bytes: u64,
    pub render_s: f64,
}

/// The training views a run uses.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase", tag = "rule")]
pub enum ViewSelection {
    /// Every training view.
    #[default]
    All,
    /// The greedy views that meet `share` of the demand of keeping every Gaussian seen by
    /// `min(k, n)` of them (`render::select`); `k` ≥ 1, `share` in (0, 1] (1: all of it).
    Cover { k: u32, share: f32 },
}

impl std::str::FromStr for ViewSelection {
    type Err = String;
    /// `all`, `K` (every Gaussian seen by K views, all of the demand) or `K:SHARE` (the
    /// greedy views that meet SHARE of it).
    fn from_str(s: &str) -> Result<ViewSelection, String> {
        if s == "all" || s == "0" {
            return Ok(ViewSelection::All);
        }
        let (k, share) = s.split_once(':').unwrap_or((s, "1"));
        let bad = || {
            format!("{s:?} is not all, K or K:SHARE (K ≥ 1 views per Gaussian, SHARE in (0, 1])")
        };
        let k: u32 = k.parse().map_err(|_| bad())?;
        let share: f32 = share.parse().map_err(|_| bad())?;
        let v = ViewSelection::Cover { k, share };
        v.validate()?;
        Ok(v)
    }
}

impl ViewSelection {
    /// Checks `k ≥ 1` and `share` in (0, 1].
    pub fn validate(&self) -> Result<(), String> {
        match *self {
            ViewSelection::All => Ok(()),
            ViewSelection::Cover { k, share } => {
                if k == 0 {
                    return Err("the view cover needs k ≥ 1 views per Gaussian".into());
                }
                if !(share > 0.0 && share <= 1.0) {
                    return Err(format!(
                        "the view cover's share must be in (0, 1], got {share}"
                    ));
                }
                Ok(())
            }
        }
    }

    /// One line for logs and reports.
    pub fn describe(&self) -> String {
        match self {
            ViewSelection::All => "every training view".into(),
            ViewSelection::Cover { k, share } => format!(
                "the greedy training views that meet {:.1} % of the demand of each Gaussian seen by {k} (or all that see it)",
                100.0 * share
            ),
        }
    }
}

/// What a cover chose, and why (`render::select`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ViewCover {
    /// Views per Gaussian asked for …
    pub k: u32,
    /// … and the share of the demand the chosen views meet.
    pub share: f32,
    /// Positions of the chosen views in the list given, ascending.
    pub chosen: Vec<usize>,
    /// Views offered.
    pub offered: usize,
    /// Gaussians seen (at a good angle) by at least one offered view.
    pub seen: usize,
    /// Their total demand `Σ min(k, n)`.
    pub demand: u64,
    /// The demand met by each view in the order the greedy took them (every view with any
    /// gain: the whole curve, past the share).
    pub gains: Vec<u64>,
    /// The positions of those views, in that order.
    pub order: Vec<usize>,
    /// Mean over the seen Gaussians of the number of offered views that see them.
    pub mean_views_offered: f64,
    /// … and of the chosen views that see them.
    pub mean_views_chosen: f64,
    pub seconds: f64,
}

/// The cache stage's `summary.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CacheSummary {
    pub gaussians: usize,
    pub skipped_gaussians: usize,
    pub options: CacheOptions,
    /// Whether every view's file stores its median-depth plane (version 4 written by the
    /// render stage); false in caches from before it, whose readers compute it from the lists.
    #[serde(default)]
    pub median_depth: bool,
    pub views: Vec<CachedView>,
    /// How the training views were chosen, when not every view given was cached
    /// (`render::select`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub selection: Option<ViewCover>,
    pub bytes: u64,
    pub render_s: f64,
    pub write_s: f64,
    pub total_s: f64,
}

impl crate::layout::Summary for CacheSummary {}

/// Path of view `stem`'s cache file in `dir`.
pub fn cache_file(dir: &Path, stem: &str) -> PathBuf {
    dir.join(format!("{stem}.contrib"))
}

/// A cache folder (written by the render stage, `render::cache::build`).
#[derive(Debug, Clone)]
pub struct Cache {
    pub dir: PathBuf,
    pub summary: CacheSummary,
    /// Views read in full through this cache and its clones ([`Cache::views_read`]).
    reads: std::sync::Arc<std::sync::atomic::AtomicUsize>,
}

impl Cache {
    /// Checks that view `stem`'s cached planes or lists, `found` = (width, height), have the
    /// size of its camera, `expected`: a file of another size is named with both (before a
    /// map of the camera's size is read at the cache's, or the other way round).
    pub fn check_size(
        &self,
        stem: &str,
        found: (usize, usize),
        expected: (usize, usize),
    ) -> Result<(), CacheError> {
        if found == expected {
            return Ok(());
        }
        Err(CacheError::Size {
            path: cache_file(&self.dir, stem),
            found,
            expected,
        })
    }

    /// `views` as this cache holds them, in their order: every view it lists (by stem), with
    /// its camera at the cached resolution (a view rendered at `1/s` of its camera's,
    /// [`crate::camera::Intrinsics::downscaled`]); views it does not list are left out. A
    /// cached size that is no such downscale of the camera is an error naming the file and
    /// both sizes.
    pub fn views_as_cached(&self, views: &[View]) -> Result<Vec<View>, CacheError> {
        let sizes: std::collections::HashMap<&str, (usize, usize)> = self
            .summary
            .views
            .iter()
            .map(|v| (v.stem.as_str(), (v.width, v.height)))
            .collect();
        crate::camera::views_at_sizes(views, |v| sizes.get(v.stem().as_str()).copied()).map_err(
            |(stem, found, expected)| CacheError::Size {
                path: cache_file(&self.dir, &stem),
                found,
                expected,
            },
        )
    }

    /// Opens a cache folder (reads its summary).
    pub fn open(dir: &Path) -> Result<Cache, CacheError> {
        Ok(Cache {
            dir: dir.to_path_buf(),
            summary: crate::layout::Summary::read(dir)?,
            reads: Default::default(),
        })
    }

    /// How many views were read in full, successfully ([`Cache::load`], [`Cache::load_into`],
    /// and the fallback of [`Cache::median_depth`]) through this cache and its clones: a
    /// stage's number of passes over the lists.
    pub fn views_read(&self) -> usize {
        self.reads.load(std::sync::atomic::Ordering::Relaxed)
    }

    fn count_read(&self) {
        self.reads
            .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    }

    /// Loads view `stem`, checking it indexes the cache's Gaussians.
    pub fn load(&self, stem: &str) -> Result<ViewContrib, CacheError> {
        let c = ViewContrib::read(&cache_file(&self.dir, stem), Some(self.summary.gaussians))?;
        self.count_read();
        Ok(c)
    }

    /// [`Cache::load`] into `view`, reusing its memory and the file buffer `buf`.
    pub fn load_into(
        &self,
        stem: &str,
        view: &mut ViewContrib,
        buf: &mut Vec<u8>,
    ) -> Result<(), CacheError> {
        view.read_into(
            &cache_file(&self.dir, stem),
            Some(self.summary.gaussians),
            buf,
        )?;
        self.count_read();
        Ok(())
    }

    /// The per-pixel planes of view `stem` only ([`ViewPlanes::read`]).
    pub fn load_planes(&self, stem: &str) -> Result<ViewPlanes, CacheError> {
        ViewPlanes::read(&cache_file(&self.dir, stem), Some(self.summary.gaussians))
    }

    /// View `stem`'s median depth per pixel: the stored plane, or, in a cache from before
    /// version 4 (its summary's `median_depth` false), [`median_depth`] of its lists with the
    /// Gaussians' `positions` and the view's `pose` (`None` there: an error naming the file).
    /// Returns the view's planes with it (their `median` taken out).
    pub fn median_depth(
        &self,
        stem: &str,
        positions: Option<&[[f32; 3]]>,
        pose: &crate::camera::Pose,
    ) -> Result<(ViewPlanes, Vec<f32>), CacheError> {
        let path = cache_file(&self.dir, stem);
        if let (false, Some(positions)) = (self.summary.median_depth, positions) {
            // One full read: the lists give the median, and the planes come with them.
            let c = ViewContrib::read(&path, Some(self.summary.gaussians))?;
            self.count_read();
            let m = if c.median.is_empty() {
                median_depth(&c, positions, pose)
            } else {
                c.median
            };
            let planes = ViewPlanes {
                width: c.width,
                height: c.height,
                alpha: c.alpha,
                depth: c.depth,
                median: None,
            };
            return Ok((planes, m));
        }
        let mut planes = self.load_planes(stem)?;
        if let Some(m) = planes.median.take() {
            return Ok((planes, m));
        }
        Err(CacheError::Format {
            path,
            why: if self.summary.median_depth {
                "no median-depth plane, though the cache's summary.json says every view has one: \
                 render the cache again"
                    .into()
            } else {
                "no median-depth plane (a cache from before version 4): its median depth needs the \
                 Gaussians' centres"
                    .into()
            },
        })
    }

    /// Whether the cache holds view `stem`.
    pub fn has(&self, stem: &str) -> bool {
        self.summary.views.iter().any(|v| v.stem == stem)
    }
}

// The pixel prediction rules: what a cached view predicts per pixel from per-Gaussian values.

/// Per-pixel predicted label and class maps of one cached view: for each pixel the label whose
/// Gaussians carry the largest weight, where `1 − α`, the truncated mass and unlabelled
/// Gaussians vote for −1; the class map is computed the same way over the Gaussians' classes.
/// Returns `(class map, label map)`.
pub fn predict(c: &ViewContrib, label: &[i32], class: &[i32]) -> (Vec<i32>, Vec<i32>) {
    (0..c.pixels())
        .into_par_iter()
        .with_min_len(4096)
        .map_init(Vec::new, |groups, p| {
            (
                pixel_value(c, p, class, groups),
                pixel_value(c, p, label, groups),
            )
        })
        .unzip()
}

/// One map of [`predict`]: per pixel, the value of `of` (per Gaussian) whose Gaussians carry
/// the largest weight, or −1 where `1 − α`, the truncated mass and the Gaussians valued −1
/// weigh more. Pixels are independent (parallel; the sums per pixel run in a fixed order).
pub fn predict_map(c: &ViewContrib, of: &[i32]) -> Vec<i32> {
    let mut out = Vec::new();
    (0..c.pixels())
        .into_par_iter()
        .with_min_len(4096)
        .map_init(Vec::new, |groups, p| pixel_value(c, p, of, groups))
        .collect_into_vec(&mut out);
    out
}

/// Pixel `p`'s value of `of` by [`pick_label`]; `groups` is scratch.
fn pixel_value(c: &ViewContrib, p: usize, of: &[i32], groups: &mut Vec<(i32, f32)>) -> i32 {
    let (ids, ws) = c.pixel(p);
    let rest = 1.0 - c.alpha[p] + c.lists.residual[p];
    pick_label(
        ids.iter().zip(ws).map(|(&g, &w)| (of[g as usize], w)),
        groups,
        rest,
    )
}

/// The label of one pixel from its `(label, weight)` entries in list order: the label with the
/// largest summed weight (sums in list order), ties to the smaller label; −1 when `rest` plus
/// the entries labelled −1 weigh at least as much. `groups` is scratch.
fn pick_label(
    entries: impl Iterator<Item = (i32, f32)>,
    groups: &mut Vec<(i32, f32)>,
    rest: f32,
) -> i32 {
    groups.clear();
    // From −0.0, as `Iterator::sum` does.
    let mut background = -0.0f32;
    for (l, w) in entries {
        if l == -1 {
            background += w;
            continue;
        }
        match groups.iter_mut().find(|g| g.0 == l) {
            Some(g) => g.1 += w,
            None => groups.push((l, 0.0 + w)),
        }
    }
    let mut best = (-1, rest + background);
    for &(l, w) in groups.iter() {
        if w > best.1 || (w == best.1 && best.0 != -1 && l < best.0) {
            best = (l, w);
        }
    }
    best.0
}

// Depth from the cache: the 3DGS median depth of a cached view.

/// The view-space z (the camera-axis depth the rasterizer sorts by) of Gaussian centres:
/// only the third row of `world_to_camera` (`R·p + t`), hoisted once per view.
pub struct CentreZ {
    row: glam::DVec3,
    tz: f64,
}

impl CentreZ {
    pub fn new(pose: &crate::camera::Pose) -> CentreZ {
        CentreZ {
            row: pose.rotation.row(2),
            tz: pose.translation.z,
        }
    }

    /// The z of centre `p`.
    #[inline]
    pub fn of(&self, p: [f32; 3]) -> f32 {
        (self
            .row
            .dot(glam::DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64))
            + self.tz) as f32
    }
}

/// The 3DGS median depth per pixel from a view's contribution lists: the z of the Gaussian
/// at which the accumulated weight `Σ α·T` (in depth order) first reaches 0.5 — where the
/// transmittance crosses 0.5, the rasterizer's median depth. NaN where the kept weights never
/// reach 0.5 (mostly transparent pixels, or mass lost to the top-k truncation), or where the
/// Gaussian has no centre in `positions`. Unlike the expected depth, it is not pulled forward
/// by semi-transparent Gaussians in front (a tree crown at 1 m covering 25 % of a wall pixel
/// at 11 m moves the expected depth to 8.6 m and the median not at all). Only the median
/// Gaussians' z is computed ([`CentreZ`], with the view's `pose`), not every centre's.
pub fn median_depth(
    c: &ViewContrib,
    positions: &[[f32; 3]],
    pose: &crate::camera::Pose,
) -> Vec<f32> {
    let z = CentreZ::new(pose);
    (0..c.pixels())
        .map(|p| {
            median_gaussian(c, p)
                .and_then(|i| positions.get(i as usize))
                .map_or(f32::NAN, |&q| z.of(q))
        })
        .collect()
}

/// The Gaussian of pixel `p` at which the accumulated weight `Σ α·T` (in depth order) first
/// reaches 0.5 (the one [`median_depth`] reads), or `None` where the kept weights never do.
pub fn median_gaussian(c: &ViewContrib, p: usize) -> Option<u32> {
    let (ids, w) = c.pixel(p);
    let mut acc = 0.0f32;
    for (&i, &wi) in ids.iter().zip(w) {
        acc += wi;
        if acc >= 0.5 {
            return Some(i);
        }
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn views_as_cached_take_the_cached_resolution_and_skip_the_rest() {
        let view = |name: &str| View {
            image_id: 1,
            camera_id: 1,
            name: format!("{name}.png"),
            camera: crate::camera::Camera {
                intrinsics: crate::camera::Intrinsics {
                    width: 100,
                    height: 80,
                    fx: 90.0,
                    fy: 91.0,
                    cx: 50.5,
                    cy: 40.0,
                    distortion: crate::camera::Distortion::None,
                },
                pose: crate::camera::Pose::look_at(
                    glam::DVec3::ZERO,
                    glam::DVec3::X,
                    glam::DVec3::Z,
                )
                .unwrap(),
            },
        };
        let cached = |stem: &str, width: usize, height: usize| CachedView {
            name: format!("{stem}.png"),
            stem: stem.into(),
            width,
            height,
            entries: 0,
            mean_list: 0.0,
            mean_dropped_share: 0.0,
            coverage: 0.0,
            bytes: 0,
            render_s: 0.0,
        };
        let mut cache = Cache {
            dir: PathBuf::from("R/render"),
            summary: CacheSummary {
                gaussians: 1,
                skipped_gaussians: 0,
                options: CacheOptions::default(),
                median_depth: true,
                views: vec![
                    cached("a", 50, 40),
                    cached("b", 100, 80),
                    cached("d", 34, 27),
                ],
                selection: None,
                bytes: 0,
                render_s: 0.0,
                write_s: 0.0,
                total_s: 0.0,
            },
            reads: Default::default(),
        };
        let views: Vec<View> = ["d", "c", "b", "a"].iter().map(|n| view(n)).collect();
        let got = cache.views_as_cached(&views).unwrap();
        // In the order given, "c" (not cached) left out; "d" at 1/3, "b" full, "a" at 1/2.
        let names: Vec<&str> = got.iter().map(|v| v.name.as_str()).collect();
        assert_eq!(names, ["d.png", "b.png", "a.png"]);
        let k = |v: &View| {
            let k = v.camera.intrinsics;
            (k.width, k.height, k.fx, k.fy, k.cx, k.cy)
        };
        assert_eq!(
            k(&got[0]),
            (34, 27, 30.0, 91.0 / 3.0, 50.5 / 3.0, 40.0 / 3.0)
        );
        assert_eq!(got[1], views[2]);
        assert_eq!(k(&got[2]), (50, 40, 45.0, 45.5, 25.25, 20.0));
        assert_eq!(got[2].camera.pose, views[3].camera.pose);
        // A cached size that no divisor makes: one line naming the file and both sizes.
        cache.summary.views.push(cached("c", 60, 40));
        let e = cache.views_as_cached(&views).unwrap_err().to_string();
        assert!(
            e.contains("c.contrib") && e.contains("60×40") && e.contains("100×80"),
            "{e}"
        );
    }

    #[test]
    fn centre_z_is_the_camera_z_of_world_to_camera_and_the_median_reads_it() {
        let pose = crate::camera::Pose::look_at(
            glam::DVec3::new(3.0, -7.0, 2.0),
            glam::DVec3::new(0.5, 1.0, 1.0),
            glam::DVec3::Z,
        )
        .unwrap();
        let pts = [[0.0f32, 0.0, 0.0], [1.5, 2.5, -0.5], [-4.0, 8.0, 3.0]];
        let cz = CentreZ::new(&pose);
        for p in pts {
            let e = pose
                .world_to_camera(glam::DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64))
                .z;
            assert!((cz.of(p) as f64 - e).abs() < 1e-5, "{} {e}", cz.of(p));
        }
        // Pixel 0: weights 0.3, 0.3 → the second Gaussian (id 2) crosses 0.5; pixel 1: 0.2 only,
        // never; pixel 2: id 7, beyond the centres.
        let mut v = ViewContrib::empty();
        v.width = 3;
        v.height = 1;
        v.lists.offsets = vec![0, 2, 3, 4];
        v.lists.ids = vec![0, 2, 1, 7];
        v.lists.weights = vec![0.3, 0.3, 0.2, 0.9];
        let d = median_depth(&v, &pts, &pose);
        assert_eq!(d[0].to_bits(), cz.of(pts[2]).to_bits());
        assert!(d[1].is_nan() && d[2].is_nan());
    }

    use rand::{Rng, SeedableRng};

    /// The rule written the plain way: sort by label, sum each run, keep the first strict
    /// maximum over the background (rest + the −1 entries).
    fn pick_by_sorting(entries: &[(i32, f32)], rest: f32) -> i32 {
        let mut acc = entries.to_vec();
        acc.sort_by_key(|x| x.0);
        let bg: f32 = acc.iter().filter(|x| x.0 == -1).map(|x| x.1).sum();
        let mut best = (-1, rest + bg);
        for chunk in acc.chunk_by(|a, b| a.0 == b.0) {
            let w = chunk.iter().fold(0.0f32, |s, x| s + x.1);
            if chunk[0].0 != -1 && w > best.1 {
                best = (chunk[0].0, w);
            }
        }
        best.0
    }

    #[test]
    fn pixel_labels_match_the_sorting_rule_including_ties() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let mut groups = Vec::new();
        for case in 0..20_000 {
            let n = rng.random_range(0..20);
            // Few labels and weights from a small set: many exact ties.
            let entries: Vec<(i32, f32)> = (0..n)
                .map(|_| {
                    (
                        rng.random_range(-1..4) * if case % 2 == 0 { 1 } else { 1000 },
                        [0.125f32, 0.25, 0.1, 0.3, 0.0][rng.random_range(0..5)],
                    )
                })
                .collect();
            let rest = [0.0f32, 0.25, 0.5, 1.0][rng.random_range(0..4)];
            assert_eq!(
                pick_label(entries.iter().copied(), &mut groups, rest),
                pick_by_sorting(&entries, rest),
                "{entries:?} rest {rest}"
            );
        }
    }

    fn sample() -> ViewContrib {
        ViewContrib {
            width: 3,
            height: 2,
            k: 2,
            gaussians: 10,
            lists: Contributions {
                offsets: vec![0, 2, 2, 3, 5, 5, 6],
                ids: vec![1, 4, 9, 0, 2, 7],
                // Exact in half precision (binary fractions with few bits).
                weights: vec![0.5, 0.25, 0.875, 0.125, 0.1875, 0.3125],
                residual: vec![0.1, 0.0, 0.0, 0.05, 0.0, 0.0],
            },
            alpha: vec![0.85, 0.0, 0.9, 0.35, 0.0, 0.3],
            depth: vec![2.0, f32::NAN, 3.0, 1.0, f32::NAN, 5.0],
            median: Vec::new(),
        }
    }

    #[test]
    fn round_trip_is_exact_and_sizes_agree() {
        let v = sample();
        let b = v.to_bytes();
        assert_eq!(b.len(), v.file_bytes());
        let r = ViewContrib::from_bytes(Path::new("x"), &b).unwrap();
        assert_eq!(r.lists, v.lists);
        assert_eq!(r.alpha, v.alpha);
        assert_eq!(r.depth[0], 2.0);
        assert!(r.depth[1].is_nan());
        assert_eq!(r.pixel(3), (&[0u32, 2][..], &[0.125f32, 0.1875][..]));
    }

    #[test]
    fn weights_are_stored_in_half_precision_within_its_bound() {
        let mut v = sample();
        let w = [0.9f32, 0.1, 0.3, 1e-6, 0.99, 3.3e-3];
        v.lists.weights = w.to_vec();
        let r = ViewContrib::from_bytes(Path::new("x"), &v.to_bytes()).unwrap();
        for (&a, &b) in w.iter().zip(&r.lists.weights) {
            let (a, b) = (f64::from(a), f64::from(b));
            // Half: 11 significant bits above 2^-14, a fixed step of 2^-24 below.
            let bound = if a >= 2f64.powi(-14) {
                a * 2f64.powi(-11)
            } else {
                2f64.powi(-25)
            };
            assert!((a - b).abs() <= bound, "{a} stored as {b}");
        }
        assert_ne!(r.lists.weights[0], 0.9, "rounded, not kept as f32");
        // Rounding what is already rounded changes nothing: render rounds once, at once.
        let mut again = r.lists.weights.clone();
        round_weights(&mut again);
        assert_eq!(again, r.lists.weights);
    }

    #[test]
    fn reading_into_a_reused_view_equals_a_fresh_read() {
        let dir = crate::fsutil::test_temp_dir().join(format!("gs4c-reuse-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let big = sample();
        // A smaller view: every reused vector must shrink to it.
        let small = ViewContrib {
            width: 1,
            height: 2,
            k: 2,
            gaussians: 10,
            lists: Contributions {
                offsets: vec![0, 1, 1],
                ids: vec![3],
                weights: vec![0.75],
                residual: vec![0.0, 0.0],
            },
            alpha: vec![0.75, 0.0],
            depth: vec![4.0, f32::NAN],
            median: Vec::new(),
        };
        let (pb, ps) = (dir.join("big.contrib"), dir.join("small.contrib"));
        big.write(&pb).unwrap();
        small.write(&ps).unwrap();
        let (mut v, mut buf) = (ViewContrib::empty(), Vec::new());
        v.read_into(&pb, Some(10), &mut buf).unwrap();
        assert_eq!(v.lists, big.lists);
        v.read_into(&ps, Some(10), &mut buf).unwrap();
        let fresh = ViewContrib::read(&ps, Some(10)).unwrap();
        assert_eq!((v.width, v.height, v.k), (1, 2, 2));
        assert_eq!(v.lists, fresh.lists);
        assert_eq!(v.lists, small.lists);
        assert_eq!(v.alpha, small.alpha);
        assert!(v.depth[1].is_nan() && v.depth[0] == 4.0 && v.depth.len() == 2);
        // A stale count is refused after a successful read, too.
        assert!(matches!(
            v.read_into(&pb, Some(11), &mut buf),
            Err(CacheError::Stale { .. })
        ));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// The header and counts of `sample()` in the layout of versions 1 and 2 (before the ids).
    fn old_header(version: u32) -> Vec<u8> {
        let mut b = Vec::new();
        b.extend_from_slice(b"GS4CCONT");
        for x in [version, 3, 2, 2] {
            b.extend_from_slice(&x.to_le_bytes());
        }
        b.extend_from_slice(&10u64.to_le_bytes());
        b.extend_from_slice(&6u64.to_le_bytes());
        b.resize(64, 0);
        for n in [2u16, 0, 1, 2, 0, 1] {
            b.extend_from_slice(&n.to_le_bytes());
        }
        b
    }

    #[test]
    fn version_1_files_with_f32_weights_are_still_read() {
        let v = sample();
        let mut b = old_header(1);
        for id in [1u32, 4, 9, 0, 2, 7] {
            b.extend_from_slice(&id.to_le_bytes());
        }
        let weights = [0.9f32, 0.1, 0.3, 1e-6, 0.99, 3.3e-3];
        for arr in [&weights[..], &v.lists.residual, &v.alpha, &v.depth] {
            for x in arr {
                b.extend_from_slice(&x.to_le_bytes());
            }
        }
        let r = ViewContrib::from_bytes(Path::new("old.contrib"), &b).unwrap();
        assert_eq!(
            r.lists.weights, weights,
            "f32 weights of version 1 are exact"
        );
        assert_eq!(r.lists.ids, v.lists.ids);
        assert_eq!(r.alpha, v.alpha);
    }

    #[test]
    fn version_2_files_with_u32_ids_are_still_read() {
        let v = sample();
        let mut b = old_header(2);
        for id in &v.lists.ids {
            b.extend_from_slice(&id.to_le_bytes());
        }
        for w in &v.lists.weights {
            b.extend_from_slice(&half::f16::from_f32(*w).to_bits().to_le_bytes());
        }
        for arr in [&v.lists.residual, &v.alpha, &v.depth] {
            for x in arr {
                b.extend_from_slice(&x.to_le_bytes());
            }
        }
        let r = ViewContrib::from_bytes(Path::new("v2.contrib"), &b).unwrap();
        assert_eq!(r.lists, v.lists);
        assert_eq!(r.alpha, v.alpha);
        // A version this program does not know is refused, naming it.
        b[8..12].copy_from_slice(&5u32.to_le_bytes());
        let e = ViewContrib::from_bytes(Path::new("v5.contrib"), &b)
            .unwrap_err()
            .to_string();
        assert!(e.contains("v5.contrib") && e.contains("version 5"), "{e}");
    }

    /// `sample()` with a median plane (NaN where a pixel has no median).
    fn with_median() -> ViewContrib {
        let mut v = sample();
        v.median = vec![2.5, f32::NAN, 3.0, 1.25, f32::NAN, -0.5];
        v
    }

    fn bits(x: &[f32]) -> Vec<u32> {
        x.iter().map(|f| f.to_bits()).collect()
    }

    #[test]
    fn the_median_plane_is_flagged_written_last_and_read_back() {
        let v = with_median();
        let b = v.to_bytes();
        assert_eq!(b.len(), v.file_bytes());
        assert_eq!(
            b.len(),
            sample().to_bytes().len() + 4 * 6,
            "one f32 per pixel more"
        );
        assert_eq!(u32::from_le_bytes(b[8..12].try_into().unwrap()), 4);
        assert_eq!(
            u32::from_le_bytes(b[48..52].try_into().unwrap()),
            FLAG_MEDIAN
        );
        // The last 24 bytes are the plane, little endian.
        let tail: Vec<u32> = b[b.len() - 24..]
            .chunks(4)
            .map(|c| u32::from_le_bytes(c.try_into().unwrap()))
            .collect();
        assert_eq!(tail, bits(&v.median));
        let r = ViewContrib::from_bytes(Path::new("x"), &b).unwrap();
        assert_eq!(bits(&r.median), bits(&v.median));
        assert_eq!(r.lists, v.lists);
        // Without the plane: flag 0, and nothing read back.
        let b0 = sample().to_bytes();
        assert_eq!(u32::from_le_bytes(b0[48..52].try_into().unwrap()), 0);
        assert!(
            ViewContrib::from_bytes(Path::new("x"), &b0)
                .unwrap()
                .median
                .is_empty()
        );
        // A plane of the wrong length is not written.
        let mut bad = with_median();
        bad.median.pop();
        assert!(bad.write_to(&mut Vec::new()).is_err());
        // An unknown flag, or a flag without its plane, is refused.
        let mut x = b.clone();
        x[48] = 3;
        let e = ViewContrib::from_bytes(Path::new("f.contrib"), &x)
            .unwrap_err()
            .to_string();
        assert!(e.contains("f.contrib") && e.contains("flags"), "{e}");
        let mut x = b0.clone();
        x[48] = 1;
        let e = ViewContrib::from_bytes(Path::new("f.contrib"), &x)
            .unwrap_err()
            .to_string();
        assert!(e.contains("bytes"), "{e}");
    }

    #[test]
    fn the_planes_reader_reads_the_tail_and_checks_the_header() {
        let dir =
            crate::fsutil::test_temp_dir().join(format!("gs4c-planes-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let (pm, p0, p3) = (
            dir.join("m.contrib"),
            dir.join("0.contrib"),
            dir.join("3.contrib"),
        );
        with_median().write(&pm).unwrap();
        sample().write(&p0).unwrap();
        // The same view as version 3 wrote it: no flags word.
        let mut b3 = sample().to_bytes();
        b3[8..12].copy_from_slice(&3u32.to_le_bytes());
        std::fs::write(&p3, &b3).unwrap();
        let v = with_median();
        let m = ViewPlanes::read(&pm, Some(10)).unwrap();
        assert_eq!((m.width, m.height), (3, 2));
        assert_eq!(bits(&m.alpha), bits(&v.alpha));
        assert_eq!(bits(&m.depth), bits(&v.depth));
        assert_eq!(m.median.as_deref().map(bits), Some(bits(&v.median)));
        for p in [&p0, &p3] {
            let r = ViewPlanes::read(p, Some(10)).unwrap();
            assert_eq!(bits(&r.alpha), bits(&v.alpha));
            assert_eq!(bits(&r.depth), bits(&v.depth));
            assert!(r.median.is_none());
        }
        assert_eq!(ViewContrib::read(&p3, Some(10)).unwrap().lists, v.lists);
        // Version 3 has no flags word: a set byte 48 changes nothing.
        b3[48] = 1;
        std::fs::write(&p3, &b3).unwrap();
        assert!(ViewPlanes::read(&p3, Some(10)).unwrap().median.is_none());
        // Versions 1 and 2 (u32 ids; f32 or half weights).
        for version in [1u32, 2] {
            let mut b = old_header(version);
            for id in &v.lists.ids {
                b.extend_from_slice(&id.to_le_bytes());
            }
            for w in &v.lists.weights {
                if version == 1 {
                    b.extend_from_slice(&w.to_le_bytes());
                } else {
                    b.extend_from_slice(&half::f16::from_f32(*w).to_bits().to_le_bytes());
                }
            }
            for arr in [&v.lists.residual, &v.alpha, &v.depth] {
                for x in arr {
                    b.extend_from_slice(&x.to_le_bytes());
                }
            }
            let p = dir.join(format!("v{version}.contrib"));
            std::fs::write(&p, &b).unwrap();
            let r = ViewPlanes::read(&p, Some(10)).unwrap();
            assert_eq!(bits(&r.alpha), bits(&v.alpha), "version {version}");
            assert_eq!(bits(&r.depth), bits(&v.depth), "version {version}");
            assert!(r.median.is_none());
        }
        // A stale count, a truncated file and a bad alpha are refused, naming the file.
        assert!(matches!(
            ViewPlanes::read(&pm, Some(11)),
            Err(CacheError::Stale { .. })
        ));
        let b = std::fs::read(&pm).unwrap();
        std::fs::write(&pm, &b[..b.len() - 1]).unwrap();
        let e = ViewPlanes::read(&pm, Some(10)).unwrap_err().to_string();
        assert!(e.contains("m.contrib") && e.contains("bytes"), "{e}");
        std::fs::write(&pm, &b[..40]).unwrap();
        let e = ViewPlanes::read(&pm, Some(10)).unwrap_err().to_string();
        assert!(e.contains("m.contrib") && e.contains("header"), "{e}");
        let mut x = b.clone();
        let a0 = x.len() - 3 * 24; // alpha, depth, median: 24 bytes each
        x[a0..a0 + 4].copy_from_slice(&f32::NAN.to_le_bytes());
        std::fs::write(&pm, &x).unwrap();
        let e = ViewPlanes::read(&pm, Some(10)).unwrap_err().to_string();
        assert!(e.contains("pixel 0") && e.contains("alpha"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// The id code by hand for `sample()`: row 0 = pixels [1, 4], [], [9]; row 1 = [0, 2],
    /// [], [7]. Every id is new (the previous pixel's list never holds it).
    #[test]
    fn the_id_code_is_the_documented_one() {
        let (code, ends) = encode_ids(&sample());
        // Row 0: 1 − 0 → zz 2 (n = 0); 4 − 1 → 6; pixel 2: n = 0, 9 − 4 → 10.
        // Row 1: 0 − 0 → 0; 2 − 0 → 4; pixel 2 (after an empty pixel): 7 − 2 → 10.
        assert_eq!(code, vec![2, 6, 10, 0, 4, 10]);
        assert_eq!(ends, vec![3, 6]);
        // A repeated id refers to the previous pixel's list: [5, 6] then [6, 300, 5].
        let v = ViewContrib {
            width: 2,
            height: 1,
            k: 0,
            gaussians: 400,
            lists: Contributions {
                offsets: vec![0, 2, 5],
                ids: vec![5, 6, 6, 300, 5],
                weights: vec![0.5; 5],
                residual: vec![0.0; 2],
            },
            alpha: vec![1.0; 2],
            depth: vec![1.0; 2],
            median: Vec::new(),
        };
        let (code, _) = encode_ids(&v);
        // 5 → zz 10; 6 − 5 → 2; then n = 2: 6 is entry 1 → 1; 300 − 6 = 294 → zz 588, + 2 =
        // 590 = 0b100_1001110 → [0xce, 0x04]; 5 is entry 0 → 0.
        assert_eq!(code, vec![10, 2, 1, 0xce, 0x04, 0]);
        let r = ViewContrib::from_bytes(Path::new("x"), &v.to_bytes()).unwrap();
        assert_eq!(r.lists, v.lists);
        // The same ids in the same order, one shifted by an insertion, one dropped:
        // [3, 8, 9] then [3, 8, 9] → indices 0, 1, 2; then [1, 3, 9]: 1 − 9 = −8 → zz 15,
        // + 3 = 18; 3 is entry 0; 9 is entry 2.
        let v = ViewContrib {
            width: 3,
            height: 1,
            k: 0,
            gaussians: 400,
            lists: Contributions {
                offsets: vec![0, 3, 6, 9],
                ids: vec![3, 8, 9, 3, 8, 9, 1, 3, 9],
                weights: vec![0.5; 9],
                residual: vec![0.0; 3],
            },
            alpha: vec![1.0; 3],
            depth: vec![1.0; 3],
            median: Vec::new(),
        };
        let (code, _) = encode_ids(&v);
        // 3 → zz 6; 8 − 3 → 10; 9 − 8 → 2.
        assert_eq!(code, vec![6, 10, 2, 0, 1, 2, 18, 0, 2]);
        let r = ViewContrib::from_bytes(Path::new("x"), &v.to_bytes()).unwrap();
        assert_eq!(r.lists, v.lists);
    }

    #[test]
    fn random_lists_round_trip_exactly() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        for case in 0..20 {
            let (w, h) = (rng.random_range(1..40), rng.random_range(1..30));
            let gaussians: u32 = if case % 2 == 0 { 50 } else { u32::MAX };
            let mut offsets = vec![0u64];
            let mut ids = Vec::new();
            for _ in 0..w * h {
                let n = rng.random_range(0..12);
                // Few distinct ids per pixel, often shared with the neighbour.
                let mut l: Vec<u32> = Vec::new();
                while l.len() < n.min(gaussians as usize) {
                    let id = if rng.random_bool(0.5) && !ids.is_empty() {
                        ids[ids.len() - 1 - rng.random_range(0..ids.len().min(8))]
                    } else {
                        rng.random_range(0..gaussians)
                    };
                    if !l.contains(&id) {
                        l.push(id);
                    }
                }
                ids.extend(&l);
                offsets.push(ids.len() as u64);
            }
            let weights: Vec<f32> = ids.iter().map(|_| 0.25).collect();
            let v = ViewContrib {
                width: w,
                height: h,
                k: 0,
                gaussians: gaussians as usize + 1,
                lists: Contributions {
                    offsets,
                    weights,
                    ids,
                    residual: vec![0.0; w * h],
                },
                alpha: vec![0.5; w * h],
                depth: vec![1.0; w * h],
                median: Vec::new(),
            };
            let b = v.to_bytes();
            assert_eq!(b.len(), v.file_bytes());
            let r = ViewContrib::from_bytes(Path::new("x"), &b).unwrap();
            assert_eq!(r.lists, v.lists, "case {case}");
        }
    }

    #[test]
    fn damaged_files_are_refused_with_a_reason() {
        let b = sample().to_bytes();
        let e = |b: &[u8]| {
            ViewContrib::from_bytes(Path::new("v.contrib"), b)
                .unwrap_err()
                .to_string()
        };
        assert!(e(&b[..b.len() - 1]).contains("bytes"), "truncated");
        let mut x = b.clone();
        x[0] = b'X';
        assert!(e(&x).contains("header"));
        let mut x = b.clone();
        x[HEADER] = 3; // pixel 0 claims 3 entries > k = 2
        assert!(e(&x).contains("more than 2"));
        // Layout: counts 12 bytes, row ends 16, code 6 ([2, 6, 10, 0, 4, 10]), weights 12.
        let code0 = HEADER + 12 + 16;
        let mut x = b.clone();
        x[code0 + 2] = 2 * 41; // pixel 2: 4 + 41 = 45 is not below 10 Gaussians
        assert!(
            e(&x).contains("pixel 2") && e(&x).contains("not below"),
            "{}",
            e(&x)
        );
        let mut x = b.clone();
        x[code0 + 1] = 0x86; // a continuation byte: the row's code runs out
        assert!(e(&x).contains("pixel"), "{}", e(&x));
        let mut x = b.clone();
        x[HEADER + 12..HEADER + 20].copy_from_slice(&5u64.to_le_bytes()); // row 0's end moved
        assert!(
            e(&x).contains("row 0") && e(&x).contains("left over"),
            "{}",
            e(&x)
        );
        let mut x = b.clone();
        x[12..16].copy_from_slice(&u32::MAX.to_le_bytes()); // width: size check before allocating
        assert!(e(&x).contains("bytes") || e(&x).contains("too large"));
        let mut x = b;
        let w0 = code0 + 6;
        x[w0..w0 + 2].copy_from_slice(&0x7e00u16.to_le_bytes()); // a half NaN
        assert!(e(&x).contains("weight 0"));
    }

    /// The vectorised range check finds what the old per-value test found (finite and in
    /// [0, 1 + 10⁻⁵]), at every position of a block, across block boundaries.
    #[test]
    fn outside_unit_finds_the_first_value_the_per_value_test_refuses() {
        let naive = |v: &[f32]| {
            v.iter()
                .position(|x| !(x.is_finite() && (0.0..=1.0 + 1e-5).contains(x)))
        };
        let specials = [
            f32::NAN,
            f32::INFINITY,
            f32::NEG_INFINITY,
            -1e-30,
            1.0 + 2e-5,
            7.0,
            -0.0,
            0.0,
            1.0,
            1.0 + 1e-5,
        ];
        let mut refused = 0;
        for len in [1usize, 7, 1023, 1024, 1025, 3000] {
            for &x in &specials {
                for at in [0, len / 2, len - 1] {
                    let mut v: Vec<f32> = (0..len).map(|i| (i % 97) as f32 / 96.0).collect();
                    v[at] = x;
                    let want = naive(&v);
                    refused += usize::from(want.is_some());
                    assert_eq!(outside_unit(&v), want, "{x} at {at} of {len}");
                }
            }
        }
        assert_eq!(refused, 6 * 3 * 6, "six of the values are outside");
        assert_eq!(outside_unit(&[]), None);
    }
}
