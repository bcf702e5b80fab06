//! SAM's prompt encoder and mask decoder computed here from the export's own weights, with the
//! work that does not depend on the prompt done once per image and the low-rank structure of
//! the two-way transformer used instead of repeating the image side per prompt.
//!
//! What SAM's decoder does per prompt (segment-anything `MaskDecoder.predict_masks`,
//! `TwoWayTransformer`): `T = 5 + points` tokens attend to the 64×64 = 4096 image tokens and the
//! image tokens attend back, twice; the image tokens are then upscaled (two 2×2 transposed
//! convolutions with a channel LayerNorm and GELUs) and dotted with one hypernetwork vector per
//! mask. The export repeats that image side for every prompt (≈ 1.8 GMAC). Here the image
//! tokens of a prompt are never materialised:
//! - after layer `l` they are `K_l = diag(σ)·k0·M_l + E·B`: `k0` the image's own tokens,
//!   `M_l = Π C·diag(γ)` the LayerNorms' centring (`C = I − 11ᵀ/d`) and scalings (fixed per
//!   model), `σ` the product of the rows' `1/std`, `E` (`N × m`) the earlier image→token
//!   attention weights (and the per-row scales of the bias vectors), `B` (`m × d`) the
//!   tokens' values through the output projections (and the bias vectors), carried to the
//!   same frame. `m` grows by `8T + 2` per layer, far below `d = 256`;
//! - every projection an attention takes of the image tokens, `K_l·W`, is `diag(σ)·(k0·M_l·W)`
//!   (once per image) plus `E·(B·W)`, and it is only ever needed against a few tokens, so the
//!   products are folded with them first: a score matrix costs `N·(inner + m)·8T` instead of
//!   `N·d·inner`;
//! - a LayerNorm needs each row's variance `|X·C|²/d` of `X = K_l + A·U + b`:
//!   `σ²·|k0·M_l·C|²` (once per image) `+ 2σ·E·(k0·M_l·C·Bᵀ)` (per image up to the prompt's
//!   `8T`-wide values) `+ E·(B·C·Bᵀ)·Eᵀ` (an `N × m × m/2` product);
//! - the first transposed convolution of the final tokens is `diag(σ)·(k0·M_L·W) + E·(B·W)`,
//!   and the upscaling runs only for a prompt with a mask that the caller keeps (its predicted
//!   IoU passes the filter), a few rows of tokens at a time, with the hypernetwork product only
//!   for those masks.
//!
//! The result equals the export's up to the rounding of the reassociated sums; `Segmenter`
//! compares the two on a probe before it uses this path, and keeps ONNX Runtime when they
//! differ (an export of another architecture, or weights it cannot find by name).
//!
//! Weights are found by the names `torch.onnx.export` keeps (`mask_decoder.…bias`,
//! `…norm1.weight`, `prompt_encoder.…`); a linear layer's folded weight is the initializer of
//! the `MatMul` whose output its bias is added to.
use std::collections::HashMap;

use faer::linalg::matmul::triangular::BlockStructure;
use faer::{Accum, MatMut, MatRef, Par};

use crate::fastmath::{exp_neg, gelu_in_place, simd};
use crate::onnxproto::{FloatTensor, Graph, GraphNode};

/// Image tokens per side.
const SIDE: usize = 64;
/// Image tokens.
const N: usize = SIDE * SIDE;
/// Attention heads of every attention block (SAM's `TwoWayTransformer`).
const HEADS: usize = 8;
/// The encoder's input side, which point coordinates are given in.
const IMG: f32 = 1024.0;
/// The low-resolution mask side.
pub const LOW: usize = 4 * SIDE;
/// Rows of image tokens the upscaling takes at a time (its buffers stay in the core's cache).
const UP_ROWS: usize = 4;

/// Why an export's weights cannot be read as SAM's decoder.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct NativeError(String);

fn err<T>(s: impl Into<String>) -> Result<T, NativeError> {
    Err(NativeError(s.into()))
}

/// `c (m×n) ← a (m×k) · b (k×n)` (or `+=`), row-major slices, one thread.
fn mm(c: &mut [f32], a: &[f32], b: &[f32], m: usize, k: usize, n: usize, add: bool) {
    mm_views(
        MatMut::from_row_major_slice_mut(c, m, n),
        MatRef::from_row_major_slice(a, m, k),
        MatRef::from_row_major_slice(b, k, n),
        add,
    );
}

fn mm_views(c: MatMut<'_, f32>, a: MatRef<'_, f32>, b: MatRef<'_, f32>, add: bool) {
    let acc = if add { Accum::Add } else { Accum::Replace };
    faer::linalg::matmul::matmul(c, acc, a, b, 1.0f32, Par::Seq);
}

/// A linear layer: `y = x·w + b`, `w` stored `in × out` row-major.
#[derive(Debug, Clone)]
struct Linear {
    w: Vec<f32>,
    b: Vec<f32>,
    din: usize,
    dout: usize,
}

impl Linear {
    /// `rows` rows of `x` through the layer.
    fn apply(&self, x: &[f32], rows: usize) -> Vec<f32> {
        let mut y = vec![0f32; rows * self.dout];
        for r in 0..rows {
            y[r * self.dout..(r + 1) * self.dout].copy_from_slice(&self.b);
        }
        mm(&mut y, x, &self.w, rows, self.din, self.dout, true);
        y
    }
}

#[derive(Debug, Clone)]
struct Norm {
    g: Vec<f32>,
    b: Vec<f32>,
    eps: f32,
}

impl Norm {
    /// LayerNorm of each row (as wide as the weights) in place.
    fn rows(&self, x: &mut [f32]) {
        let w = self.g.len();
        simd(
            #[inline(always)]
            || {
                for row in x.chunks_exact_mut(w) {
                    let (mu, s) = stats(row, self.eps);
                    for ((v, g), b) in row.iter_mut().zip(&self.g).zip(&self.b) {
                        *v = (*v - mu) * s * g + b;
                    }
                }
            },
        )
    }
}

/// Sum of a row in eight interleaved partial sums (vectorises).
#[inline(always)]
fn sum8(row: &[f32], f: impl Fn(f32) -> f32) -> f32 {
    let mut acc = [0f32; 8];
    let chunks = row.chunks_exact(8);
    let rest: f32 = chunks.remainder().iter().map(|&v| f(v)).sum();
    for c in chunks {
        for k in 0..8 {
            acc[k] += f(c[k]);
        }
    }
    acc.iter().sum::<f32>() + rest
}

/// Mean and `1/√(var + eps)` of one row (two passes).
#[inline(always)]
fn stats(row: &[f32], eps: f32) -> (f32, f32) {
    let n = row.len() as f32;
    let mu = sum8(row, |v| v) / n;
    let var = sum8(row, |v| (v - mu) * (v - mu)) / n;
    (mu, 1.0 / (var + eps).sqrt())
}

#[derive(Debug, Clone)]
struct Attn {
    q: Linear,
    k: Linear,
    v: Linear,
    o: Linear,
}

impl Attn {
    fn inner(&self) -> usize {
        self.q.dout
    }
    fn head(&self) -> usize {
        self.q.dout / HEADS
    }
}

#[derive(Debug, Clone)]
struct Layer {
    self_attn: Attn,
    norm1: Norm,
    t2i: Attn,
    norm2: Norm,
    mlp1: Linear,
    mlp2: Linear,
    norm3: Norm,
    i2t: Attn,
    norm4: Norm,
}

/// A projection `W` (`d × k`) that an attention applies to the image tokens, carried to the
/// frame of one level: `M_l·W`, and `pe·W` where the projection reads the positional
/// encoding too.
#[derive(Debug, Clone)]
struct Consumer {
    /// `M_l·W`, `d × k`.
    mw: Vec<f32>,
    k: usize,
    /// `pe·W`, `N × k`, column-major.
    pe: Option<Vec<f32>>,
}

impl Consumer {
    /// The positional term a prompt adds at level `l`: at level 0 it is already in the
    /// image's projection ([`SamDecoder::prepare`]).
    fn pe_after(&self, l: usize) -> Option<&[f32]> {
        self.pe.as_deref().filter(|_| l > 0)
    }
}

/// What the LayerNorm after layer `l`'s image→token attention needs of the image: the row
/// norms' cross terms `M_l·C·Qᵀ`, with `Q` the rows a prompt's low-rank part is built from
/// (each earlier layer's output projection and bias vectors, carried to this level's frame).
#[derive(Debug, Clone)]
struct LnLevel {
    /// `M_l·C·[Q blocks]`, `d × width`.
    hmat: Vec<f32>,
    width: usize,
    /// `M_l·C`, `d × d` (the image part's own squared norms).
    mc: Vec<f32>,
}

/// SAM's prompt encoder (points only, no mask prompt) and mask decoder.
#[derive(Debug, Clone)]
pub struct SamDecoder {
    d: usize,
    layers: Vec<Layer>,
    final_attn: Attn,
    norm_final: Norm,
    /// The IoU token and the mask tokens, `(1 + masks) × d`.
    tokens: Vec<f32>,
    masks: usize,
    /// Random Fourier features, `2 × d/2`.
    gauss: Vec<f32>,
    not_a_point: Vec<f32>,
    point_embed: Vec<Vec<f32>>,
    no_mask: Vec<f32>,
    /// First transposed convolution as `d × 4·c1`, column `s·c1 + c` (`s = 2·ky + kx`).
    up1_w: Vec<f32>,
    up1_b: Vec<f32>,
    c1: usize,
    ln2d: Norm,
    /// Second transposed convolution as `c1 × 4·c2`, column `s·c2 + c`.
    up2_w: Vec<f32>,
    up2_b: Vec<f32>,
    c2: usize,
    hyper: Vec<Vec<Linear>>,
    iou_head: Vec<Linear>,
    /// Per layer: the token→image keys and values, the image→token queries.
    t2i_k: Vec<Consumer>,
    t2i_v: Vec<Consumer>,
    i2t_q: Vec<Consumer>,
    /// The final attention's keys and values, and the first convolution (level `L`).
    fin_k: Consumer,
    fin_v: Consumer,
    up: Consumer,
    ln: Vec<LnLevel>,
}

/// What one image gives every prompt: the image tokens `k0` through every consumer's
/// `M_l·W` (`N × k`, column-major; at level 0 with `pe·W` added) and through each LayerNorm
/// level's terms.
pub struct ImagePrep {
    pk: Vec<Vec<f32>>,
    pv: Vec<Vec<f32>>,
    pq: Vec<Vec<f32>>,
    fk: Vec<f32>,
    fv: Vec<f32>,
    /// `k0·M_L·W_up1`, `N × 4·c1`.
    c0: Vec<f32>,
    /// Per level: `k0·hmat` (`N × width`, column-major) and the squared row norms of
    /// `k0·M_l·C`.
    h: Vec<Vec<f32>>,
    n: Vec<Vec<f32>>,
}

/// A prompt's image tokens at some level `l`, never materialised:
/// `K_l = diag(σ)·k0·M_l + E·B` (before the positional encoding), with `E` (`N × m`,
/// column-major) the attention weights of the earlier image→token attentions and the
/// per-row scale columns of bias vectors, and `B` (`m × d`) their rows in this level's frame.
struct Side {
    /// `None`: all ones (level 0).
    sigma: Option<Vec<f32>>,
    e: Vec<f32>,
    b: Vec<f32>,
    m: usize,
    /// Each layer's image→token values (`t × inner`), for the LayerNorms' cross terms.
    vv: Vec<Vec<f32>>,
}

/// A decoded prompt: the predicted IoU of each mask and what the upscaling needs.
pub struct Decoded {
    pub iou: Vec<f32>,
    hyper: Vec<Vec<f32>>,
    side: Side,
}

struct Lookup<'a> {
    /// By state-dict name (from `mask_decoder.` or `prompt_encoder.` on).
    by_name: HashMap<String, &'a FloatTensor>,
    /// State-dict name → the graph's name.
    real: HashMap<String, &'a str>,
    /// By the graph's name (initializers and `Identity` copies of them).
    by_real: HashMap<&'a str, &'a FloatTensor>,
    /// The node that computes each value.
    producers: HashMap<&'a str, &'a GraphNode>,
    g: &'a Graph,
}

impl<'a> Lookup<'a> {
    fn new(g: &'a Graph) -> Lookup<'a> {
        let mut by_name = HashMap::new();
        let mut real = HashMap::new();
        // torch's export replaces an initializer equal to another by an `Identity` of it
        let mut named: Vec<(&'a str, &'a FloatTensor)> = g
            .initializers
            .iter()
            .map(|(n, t)| (n.as_str(), t))
            .collect();
        // By name: should two initializers shorten to one key below, the same one wins in every
        // process (the map's own order is seeded at random).
        named.sort_unstable_by_key(|&(n, _)| n);
        for n in &g.nodes {
            if let (true, [i], [o]) = (n.op_type == "Identity", &n.inputs[..], &n.outputs[..]) {
                if let Some(t) = g.initializers.get(i) {
                    named.push((o.as_str(), t));
                }
            }
        }
        let by_real: HashMap<&str, &FloatTensor> = named.iter().copied().collect();
        for (name, t) in named {
            let key = ["mask_decoder.", "prompt_encoder."]
                .iter()
                .filter_map(|p| name.rfind(p))
                .min()
                .map_or(name, |i| &name[i..]);
            by_name.insert(key.to_string(), t);
            real.insert(key.to_string(), name);
        }
        let producers = g
            .nodes
            .iter()
            .flat_map(|n| n.outputs.iter().map(move |o| (o.as_str(), n)))
            .collect();
        Lookup {
            by_name,
            real,
            by_real,
            producers,
            g,
        }
    }

    fn get(&self, key: &str) -> Option<&'a FloatTensor> {
        self.by_name.get(key).copied()
    }

    fn need(&self, key: &str, len: usize) -> Result<Vec<f32>, NativeError> {
        match self.get(key) {
            Some(t) if t.data.len() == len => Ok(t.data.clone()),
            Some(t) => err(format!("{key} has {} values, expected {len}", t.data.len())),
            None => err(format!("no initializer {key}")),
        }
    }

    fn unique_by_dims(&self, dims: &[&[usize]]) -> Option<&'a FloatTensor> {
        let hits: Vec<&FloatTensor> = self
            .g
            .initializers
            .values()
            .filter(|t| dims.iter().any(|d| t.dims == *d))
            .collect();
        match hits.as_slice() {
            [one] => Some(one),
            _ => None,
        }
    }

    /// The linear layer `path`: a named `weight` (`out × in`) or the `MatMul` initializer
    /// (`in × out`) whose output the named bias is added to.
    fn linear(&self, path: &str) -> Result<Linear, NativeError> {
        let bias = self
            .get(&format!("{path}.bias"))
            .ok_or_else(|| NativeError(format!("no initializer {path}.bias")))?;
        let dout = bias.data.len();
        if let Some(w) = self.get(&format!("{path}.weight")) {
            if w.dims.len() != 2 || w.dims[0] != dout {
                return err(format!("{path}.weight has dims {:?}", w.dims));
            }
            let din = w.dims[1];
            let mut t = vec![0f32; din * dout];
            for o in 0..dout {
                for i in 0..din {
                    t[i * dout + o] = w.data[o * din + i];
                }
            }
            return Ok(Linear {
                w: t,
                b: bias.data.clone(),
                din,
                dout,
            });
        }
        let bias_name = self.real[&format!("{path}.bias")];
        for add in self
            .g
            .nodes
            .iter()
            .filter(|n| n.op_type == "Add" && n.inputs.iter().any(|i| i == bias_name))
        {
            for other in add.inputs.iter().filter(|i| *i != bias_name) {
                let Some(mm) = self.producers.get(other.as_str()) else {
                    continue;
                };
                if mm.op_type != "MatMul" {
                    continue;
                }
                if let Some(w) = mm
                    .inputs
                    .iter()
                    .filter_map(|i| self.by_real.get(i.as_str()).copied())
                    .find(|w| w.dims.len() == 2 && w.dims[1] == dout)
                {
                    return Ok(Linear {
                        w: w.data.clone(),
                        b: bias.data.clone(),
                        din: w.dims[0],
                        dout,
                    });
                }
            }
        }
        err(format!("no weight found for {path}"))
    }

    fn norm(&self, path: &str, eps: f32) -> Result<Norm, NativeError> {
        let g = self
            .get(&format!("{path}.weight"))
            .ok_or_else(|| NativeError(format!("no initializer {path}.weight")))?;
        let n = g.data.len();
        Ok(Norm {
            g: g.data.clone(),
            b: self.need(&format!("{path}.bias"), n)?,
            eps,
        })
    }

    fn attn(&self, path: &str) -> Result<Attn, NativeError> {
        let a = Attn {
            q: self.linear(&format!("{path}.q_proj"))?,
            k: self.linear(&format!("{path}.k_proj"))?,
            v: self.linear(&format!("{path}.v_proj"))?,
            o: self.linear(&format!("{path}.out_proj"))?,
        };
        if a.inner() % HEADS != 0 || a.k.dout != a.inner() || a.v.dout != a.inner() {
            return err(format!(
                "{path}: projections of widths {} {} {}",
                a.q.dout, a.k.dout, a.v.dout
            ));
        }
        Ok(a)
    }

    fn mlp(&self, path: &str) -> Result<Vec<Linear>, NativeError> {
        let mut v = Vec::new();
        while self
            .get(&format!("{path}.layers.{}.bias", v.len()))
            .is_some()
        {
            v.push(self.linear(&format!("{path}.layers.{}", v.len()))?);
        }
        if v.is_empty() {
            return err(format!("no layers for {path}"));
        }
        Ok(v)
    }

    /// The channel LayerNorm of the upscaling: named, or folded by the export into the
    /// `[c, 1, 1]` operands of the `Mul` and `Add` nodes of its scope.
    fn ln2d(&self, c: usize) -> Result<Norm, NativeError> {
        const PATH: &str = "mask_decoder.output_upscaling.1";
        if self.get(&format!("{PATH}.weight")).is_some() {
            return self.norm(PATH, 1e-6);
        }
        let mut found: [Option<Vec<f32>>; 2] = [None, None];
        for n in &self.g.nodes {
            let slot = match n.op_type.as_str() {
                "Mul" => 0,
                "Add" => 1,
                _ => continue,
            };
            if !n.name.contains("output_upscaling.1/") {
                continue;
            }
            for i in &n.inputs {
                if let Some(t) = self.by_real.get(i.as_str()) {
                    if t.dims == [c, 1, 1] {
                        found[slot] = Some(t.data.clone());
                    }
                }
            }
        }
        match found {
            [Some(g), Some(b)] => Ok(Norm { g, b, eps: 1e-6 }),
            _ => err("the upscaling's channel LayerNorm weights were not found"),
        }
    }
}

impl SamDecoder {
    /// Reads SAM's decoder from an export's graph.
    pub fn from_graph(g: &Graph) -> Result<SamDecoder, NativeError> {
        let w = Lookup::new(g);
        let mut layers = Vec::new();
        while w
            .get(&format!(
                "mask_decoder.transformer.layers.{}.norm1.weight",
                layers.len()
            ))
            .is_some()
        {
            let p = format!("mask_decoder.transformer.layers.{}", layers.len());
            layers.push(Layer {
                self_attn: w.attn(&format!("{p}.self_attn"))?,
                norm1: w.norm(&format!("{p}.norm1"), 1e-5)?,
                t2i: w.attn(&format!("{p}.cross_attn_token_to_image"))?,
                norm2: w.norm(&format!("{p}.norm2"), 1e-5)?,
                mlp1: w.linear(&format!("{p}.mlp.lin1"))?,
                mlp2: w.linear(&format!("{p}.mlp.lin2"))?,
                norm3: w.norm(&format!("{p}.norm3"), 1e-5)?,
                i2t: w.attn(&format!("{p}.cross_attn_image_to_token"))?,
                norm4: w.norm(&format!("{p}.norm4"), 1e-5)?,
            });
        }
        if layers.is_empty() {
            return err("no transformer layers (mask_decoder.transformer.layers.0.norm1.weight)");
        }
        let final_attn = w.attn("mask_decoder.transformer.final_attn_token_to_image")?;
        let norm_final = w.norm("mask_decoder.transformer.norm_final_attn", 1e-5)?;
        let d = norm_final.g.len();
        let mut hyper = Vec::new();
        while w
            .get(&format!(
                "mask_decoder.output_hypernetworks_mlps.{}.layers.0.bias",
                hyper.len()
            ))
            .is_some()
        {
            hyper.push(w.mlp(&format!(
                "mask_decoder.output_hypernetworks_mlps.{}",
                hyper.len()
            ))?);
        }
        let masks = hyper.len();
        if masks == 0 {
            return err("no output hypernetworks");
        }
        let iou_head = w.mlp("mask_decoder.iou_prediction_head")?;
        let tokens = match (
            w.get("mask_decoder.iou_token.weight"),
            w.get("mask_decoder.mask_tokens.weight"),
        ) {
            (Some(a), Some(b)) => [a.data.clone(), b.data.clone()].concat(),
            _ => w
                .unique_by_dims(&[&[1, 1 + masks, d], &[1 + masks, d]])
                .ok_or_else(|| NativeError("the output tokens were not found".into()))?
                .data
                .clone(),
        };
        if tokens.len() != (1 + masks) * d {
            return err("the output tokens have the wrong size");
        }
        let no_mask = match w.get("prompt_encoder.no_mask_embed.weight") {
            Some(t) => t.data.clone(),
            None => w
                .unique_by_dims(&[&[1, d, 1, 1]])
                .ok_or_else(|| NativeError("the no-mask embedding was not found".into()))?
                .data
                .clone(),
        };
        if no_mask.len() != d || d % 2 != 0 {
            return err("the no-mask embedding has the wrong size");
        }
        let gauss = w.need(
            "prompt_encoder.pe_layer.positional_encoding_gaussian_matrix",
            d,
        )?;
        let not_a_point = w.need("prompt_encoder.not_a_point_embed.weight", d)?;
        let point_embed = (0..2)
            .map(|i| w.need(&format!("prompt_encoder.point_embeddings.{i}.weight"), d))
            .collect::<Result<Vec<_>, _>>()?;
        let up1 = w
            .get("mask_decoder.output_upscaling.0.weight")
            .ok_or_else(|| NativeError("no mask_decoder.output_upscaling.0.weight".into()))?;
        let up2 = w
            .get("mask_decoder.output_upscaling.3.weight")
            .ok_or_else(|| NativeError("no mask_decoder.output_upscaling.3.weight".into()))?;
        let (c1, c2) = (
            up1.dims.get(1).copied().unwrap_or(0),
            up2.dims.get(1).copied().unwrap_or(0),
        );
        if up1.dims != [d, c1, 2, 2] || up2.dims != [c1, c2, 2, 2] {
            return err(format!(
                "upscaling convolutions of dims {:?} and {:?}",
                up1.dims, up2.dims
            ));
        }
        // `[cin, cout, ky, kx]` → `cin × (s·cout + c)`
        let conv = |t: &FloatTensor, cin: usize, cout: usize| {
            let mut m = vec![0f32; cin * 4 * cout];
            for i in 0..cin {
                for o in 0..cout {
                    for s in 0..4 {
                        m[i * 4 * cout + s * cout + o] = t.data[(i * cout + o) * 4 + s];
                    }
                }
            }
            m
        };
        let up1_w = conv(up1, d, c1);
        let up2_w = conv(up2, c1, c2);
        let b1 = w.need("mask_decoder.output_upscaling.0.bias", c1)?;
        let b2 = w.need("mask_decoder.output_upscaling.3.bias", c2)?;
        let up1_b: Vec<f32> = (0..4 * c1).map(|k| b1[k % c1]).collect();
        let up2_b: Vec<f32> = (0..4 * c2).map(|k| b2[k % c2]).collect();
        let ln2d = w.ln2d(c1)?;
        for (i, h) in hyper.iter().enumerate() {
            if h.last().map(|l| l.dout) != Some(c2) || h[0].din != d {
                return err(format!("hypernetwork {i} does not map {d} to {c2}"));
            }
        }
        if iou_head[0].din != d || iou_head.last().map(|l| l.dout) != Some(masks) {
            return err("the IoU head does not give one score per mask");
        }
        for (i, l) in layers.iter().enumerate() {
            let ok = l.self_attn.q.din == d
                && l.self_attn.o.dout == d
                && l.t2i.q.din == d
                && l.t2i.o.dout == d
                && l.i2t.q.din == d
                && l.i2t.o.dout == d
                && l.mlp1.din == d
                && l.mlp2.dout == d
                && l.mlp2.din == l.mlp1.dout
                && [&l.norm1, &l.norm2, &l.norm3, &l.norm4]
                    .iter()
                    .all(|n| n.g.len() == d);
            if !ok {
                return err(format!("transformer layer {i} has unexpected widths"));
            }
        }
        if final_attn.q.din != d || final_attn.o.dout != d {
            return err("the final attention has unexpected widths");
        }
        // the image's positional encoding: the Fourier features of the token centres
        let mut image_pe = vec![0f32; N * d];
        for y in 0..SIDE {
            for x in 0..SIDE {
                let c = [
                    ((x as f32 + 0.5) / SIDE as f32) * 2.0 - 1.0,
                    ((y as f32 + 0.5) / SIDE as f32) * 2.0 - 1.0,
                ];
                let i = y * SIDE + x;
                fourier_features(&gauss, c, &mut image_pe[i * d..(i + 1) * d]);
            }
        }
        // the LayerNorms' frames (module docs): M_0 = I, M_{l+1} = M_l·C·diag(γ_l)
        let nl = layers.len();
        let eye: Vec<f64> = (0..d * d)
            .map(|k| if k / d == k % d { 1.0 } else { 0.0 })
            .collect();
        let centre: Vec<f64> = eye.iter().map(|v| v - 1.0 / d as f64).collect();
        let cg: Vec<Vec<f64>> = layers
            .iter()
            .map(|l| {
                (0..d * d)
                    .map(|k| centre[k] * f64::from(l.norm4.g[k % d]))
                    .collect()
            })
            .collect();
        let mut ms = vec![eye.clone()];
        for l in 0..nl {
            let next = mul64(&ms[l], &cg[l], d, d, d);
            ms.push(next);
        }
        // F(l, m) = C·diag(γ_m) ⋯ C·diag(γ_{l−1}): a row added after layer m, in level l's frame
        let frame =
            |l: usize, m: usize| (m..l).fold(eye.clone(), |f, k| mul64(&f, &cg[k], d, d, d));
        let consumer = |m: &[f64], w: &[f32], k: usize, pe: bool| Consumer {
            mw: to32(&mul64(m, &to64(w), d, d, k)),
            k,
            pe: pe.then(|| {
                let mut o = vec![0f32; N * k];
                mm_views(
                    cm_mut(&mut o, N, k),
                    rm(&image_pe, N, d),
                    rm(w, d, k),
                    false,
                );
                o
            }),
        };
        let lin = |m: &[f64], l: &Linear, pe: bool| consumer(m, &l.w, l.dout, pe);
        let t2i_k = (0..nl)
            .map(|l| lin(&ms[l], &layers[l].t2i.k, true))
            .collect();
        let t2i_v = (0..nl)
            .map(|l| lin(&ms[l], &layers[l].t2i.v, false))
            .collect();
        let i2t_q = (0..nl)
            .map(|l| lin(&ms[l], &layers[l].i2t.q, true))
            .collect();
        let fin_k = lin(&ms[nl], &final_attn.k, true);
        let fin_v = lin(&ms[nl], &final_attn.v, false);
        let up = consumer(&ms[nl], &up1_w, 4 * c1, false);
        let ln = (0..nl)
            .map(|l| {
                // the rows of a prompt's low-rank part at layer l's LayerNorm, in the order
                // `Side` appends them: per layer m its output projection and bias, then (m < l)
                // its LayerNorm's β
                let mut cols: Vec<Vec<f64>> = Vec::new();
                for (m, lm) in layers.iter().enumerate().take(l + 1) {
                    let f = frame(l, m);
                    let o = &lm.i2t.o;
                    let wf = mul64(&to64(&o.w), &f, o.din, d, d);
                    cols.extend(wf.chunks_exact(d).map(<[f64]>::to_vec));
                    cols.push(mul64(&to64(&o.b), &f, 1, d, d));
                    if m < l {
                        cols.push(mul64(&to64(&lm.norm4.b), &frame(l, m + 1), 1, d, d));
                    }
                }
                let width = cols.len();
                let mut q = vec![0f64; d * width];
                for (c, col) in cols.iter().enumerate() {
                    for i in 0..d {
                        q[i * width + c] = col[i];
                    }
                }
                let mc = mul64(&ms[l], &centre, d, d, d);
                LnLevel {
                    hmat: to32(&mul64(&mc, &q, d, d, width)),
                    width,
                    mc: to32(&mc),
                }
            })
            .collect();
        Ok(SamDecoder {
            d,
            layers,
            final_attn,
            norm_final,
            tokens,
            masks,
            gauss,
            not_a_point,
            point_embed,
            no_mask,
            up1_w,
            up1_b,
            c1,
            ln2d,
            up2_w,
            up2_b,
            c2,
            hyper,
            iou_head,
            t2i_k,
            t2i_v,
            i2t_q,
            fin_k,
            fin_v,
            up,
            ln,
        })
    }

    /// Masks per prompt.
    pub fn masks(&self) -> usize {
        self.masks
    }

    /// SAM's random Fourier features of a point in `[−1, 1]²`.
    fn fourier(&self, c: [f32; 2], out: &mut [f32]) {
        fourier_features(&self.gauss, c, out);
    }

    /// The per-image work: `embeddings` is the encoder's `[256, 64, 64]` output.
    pub fn prepare(&self, embeddings: &[f32]) -> ImagePrep {
        let d = self.d;
        let mut k0 = vec![0f32; N * d];
        for c in 0..d {
            for i in 0..N {
                k0[i * d + c] = embeddings[c * N + i] + self.no_mask[c];
            }
        }
        // column-major, so that a head's columns are one contiguous block
        let times = |w: &[f32], k: usize| {
            let mut p = vec![0f32; N * k];
            mm_views(cm_mut(&mut p, N, k), rm(&k0, N, d), rm(w, d, k), false);
            p
        };
        // level 0 reads `k0 + pe` directly: its positional term is added here
        let through = |c: &Consumer, level0: bool| {
            let mut p = times(&c.mw, c.k);
            if let (true, Some(pe)) = (level0, &c.pe) {
                add_in_place(&mut p, pe);
            }
            p
        };
        let nl = self.layers.len();
        ImagePrep {
            pk: (0..nl).map(|l| through(&self.t2i_k[l], l == 0)).collect(),
            pv: (0..nl).map(|l| through(&self.t2i_v[l], l == 0)).collect(),
            pq: (0..nl).map(|l| through(&self.i2t_q[l], l == 0)).collect(),
            fk: through(&self.fin_k, false),
            fv: through(&self.fin_v, false),
            c0: {
                let mut c0 = vec![0f32; N * self.up.k];
                mm(&mut c0, &k0, &self.up.mw, N, d, self.up.k, false);
                c0
            },
            h: self.ln.iter().map(|lv| times(&lv.hmat, lv.width)).collect(),
            n: self
                .ln
                .iter()
                .map(|lv| {
                    let mut x = vec![0f32; N * d];
                    mm(&mut x, &k0, &lv.mc, N, d, d, false);
                    x.chunks_exact(d)
                        .map(|r| r.iter().map(|&v| f64::from(v) * f64::from(v)).sum::<f64>() as f32)
                        .collect()
                })
                .collect(),
        }
    }

    /// The prompt tokens of points in the 1024 frame with labels (1 foreground, 0 background,
    /// −1 padding), as SAM's export embeds them. Box corners (labels 2 and 3) are not read
    /// from the export and must not be given.
    fn prompt_tokens(&self, points: &[[f32; 2]], labels: &[f32]) -> Vec<f32> {
        let d = self.d;
        let mut t = self.tokens.clone();
        for (p, &l) in points.iter().zip(labels) {
            let mut e = vec![0f32; d];
            if l == -1.0 {
                e.copy_from_slice(&self.not_a_point);
            } else {
                let c = [
                    (p[0] + 0.5) / IMG * 2.0 - 1.0,
                    (p[1] + 0.5) / IMG * 2.0 - 1.0,
                ];
                self.fourier(c, &mut e);
                if let Some(pe) = self.point_embed.get(l as usize).filter(|_| l >= 0.0) {
                    for (a, b) in e.iter_mut().zip(pe) {
                        *a += b;
                    }
                }
            }
            t.extend_from_slice(&e);
        }
        t
    }

    /// Decodes one prompt up to the tokens: the predicted IoU of each mask, and what
    /// [`SamDecoder::low_res`] needs. `labels` are 1, 0 or −1 (no box corners).
    pub fn decode(&self, prep: &ImagePrep, points: &[[f32; 2]], labels: &[f32]) -> Decoded {
        let d = self.d;
        let tok = self.prompt_tokens(points, labels);
        let t = tok.len() / d;
        let mut q = tok.clone();
        // E and B grow by HEADS·t + 2 columns and rows per layer
        let cap = self.layers.len() * (HEADS * t + 2);
        let mut side = Side {
            sigma: None,
            e: Vec::with_capacity(N * cap),
            b: Vec::with_capacity(d * cap),
            m: 0,
            vv: Vec::new(),
        };
        for (l, layer) in self.layers.iter().enumerate() {
            // self-attention (the first layer without positional terms or residual)
            if l == 0 {
                q = self_attention(&layer.self_attn, &q, &q, &q, t);
            } else {
                let qq = plus(&q, &tok);
                let a = self_attention(&layer.self_attn, &qq, &qq, &q, t);
                add_in_place(&mut q, &a);
            }
            layer.norm1.rows(&mut q);
            // token → image
            let qq = plus(&q, &tok);
            let pe = self.t2i_k[l].pe_after(l);
            let a = self.token_to_image(&layer.t2i, &qq, t, &side, (&prep.pk[l], &prep.pv[l]), pe);
            add_in_place(&mut q, &a);
            layer.norm2.rows(&mut q);
            // MLP
            let mut h = layer.mlp1.apply(&q, t);
            h.iter_mut().for_each(|v| *v = v.max(0.0));
            let m = layer.mlp2.apply(&h, t);
            add_in_place(&mut q, &m);
            layer.norm3.rows(&mut q);
            // image → token: the image tokens' queries against the tokens' keys, softmax over
            // the tokens of each head
            let qq = plus(&q, &tok);
            let att = &layer.i2t;
            let scale = 1.0 / (att.head() as f32).sqrt();
            let mut kk = att.k.apply(&qq, t);
            kk.iter_mut().for_each(|v| *v *= scale);
            let vv = att.v.apply(&q, t);
            let pe = self.i2t_q[l].pe_after(l);
            let mut a = self.scores(&side, &prep.pq[l], pe, &att.q, &kk, t);
            softmax_heads(&mut a, t);
            self.norm_step(&mut side, l, a, vv, t, (&prep.h[l], &prep.n[l]));
        }
        // final token → image attention, for the output tokens only
        let to = 1 + self.masks;
        let qq = plus(&q[..to * d], &tok[..to * d]);
        let a = self.token_to_image(
            &self.final_attn,
            &qq,
            to,
            &side,
            (&prep.fk, &prep.fv),
            self.fin_k.pe.as_deref(),
        );
        let mut out = q[..to * d].to_vec();
        add_in_place(&mut out, &a);
        self.norm_final.rows(&mut out);
        let iou = mlp(&self.iou_head, &out[..d]);
        let hyper = (0..self.masks)
            .map(|m| mlp(&self.hyper[m], &out[(1 + m) * d..(2 + m) * d]))
            .collect();
        Decoded { iou, hyper, side }
    }

    /// Token→image attention of `rows` query tokens `qq` on the image tokens `side`, whose
    /// projections by the keys' and values' weights are `kv.0` and `kv.1` (`k0·M_l·W`; `pe`
    /// the keys' positional term where it is not in `kv.0`); returns the output projection,
    /// `rows × d`.
    fn token_to_image(
        &self,
        att: &Attn,
        qq: &[f32],
        rows: usize,
        side: &Side,
        kv: (&[f32], &[f32]),
        pe: Option<&[f32]>,
    ) -> Vec<f32> {
        let scale = 1.0 / (att.head() as f32).sqrt();
        let mut qs = att.q.apply(qq, rows);
        qs.iter_mut().for_each(|v| *v *= scale);
        let mut s = self.scores(side, kv.0, pe, &att.k, &qs, rows);
        softmax_columns(&mut s);
        let o = self.values(side, kv.1, &att.v, &s, rows);
        att.o.apply(&o, rows)
    }

    /// Attention scores of the image tokens `side` projected by `lin` (`p` = `k0·M_l·W`,
    /// `pe` = `pe·W` where not in `p`) against `rows` projected, scaled tokens `qs`
    /// (`rows × inner`): column-major `N × HEADS·rows`, column `h·rows + j`. With
    /// `K_l = diag(σ)·k0·M_l + E·B`: `diag(σ)·p_h·qs_hᵀ + pe_h·qs_hᵀ + E·(B·W_h·qs_hᵀ) + b_h·qs_h`.
    fn scores(
        &self,
        side: &Side,
        p: &[f32],
        pe: Option<&[f32]>,
        lin: &Linear,
        qs: &[f32],
        rows: usize,
    ) -> Vec<f32> {
        let d = self.d;
        let inner = lin.dout;
        let dh = inner / HEADS;
        let hr = HEADS * rows;
        let qv = rm(qs, rows, inner);
        let mut s = vec![0f32; N * hr];
        for (src, add) in [(Some(p), false), (pe, true)] {
            let Some(src) = src else { continue };
            for h in 0..HEADS {
                mm_views(
                    cm_mut(&mut s, N, hr).subcols_mut(h * rows, rows),
                    cm(src, N, inner).subcols(h * dh, dh),
                    qv.subcols(h * dh, dh).transpose(),
                    add,
                );
            }
            if let (false, Some(sig)) = (add, &side.sigma) {
                scale_columns(&mut s, sig);
            }
        }
        if side.m > 0 {
            let mut r = vec![0f32; d * hr];
            for h in 0..HEADS {
                mm_views(
                    rm_mut(&mut r, d, hr).subcols_mut(h * rows, rows),
                    rm(&lin.w, d, inner).subcols(h * dh, dh),
                    qv.subcols(h * dh, dh).transpose(),
                    false,
                );
            }
            let mut br = vec![0f32; side.m * hr];
            mm(&mut br, &side.b, &r, side.m, d, hr, false);
            mm_views(
                cm_mut(&mut s, N, hr),
                cm(&side.e, N, side.m),
                rm(&br, side.m, hr),
                true,
            );
        }
        for h in 0..HEADS {
            for j in 0..rows {
                let c: f32 = (0..dh)
                    .map(|c| lin.b[h * dh + c] * qs[j * inner + h * dh + c])
                    .sum();
                let col = h * rows + j;
                s[col * N..(col + 1) * N].iter_mut().for_each(|v| *v += c);
            }
        }
        s
    }

    /// The values a token→image attention takes with weights `p` (column-major
    /// `N × HEADS·rows`, each column summing to 1): `Σ_i p_i·(K_l·W_v + b_v)` per head,
    /// `rows × inner`, with `pv` = `k0·M_l·W_v`.
    fn values(&self, side: &Side, pv: &[f32], lin: &Linear, p: &[f32], rows: usize) -> Vec<f32> {
        let d = self.d;
        let inner = lin.dout;
        let dh = inner / HEADS;
        let hr = HEADS * rows;
        let mut o = vec![0f32; rows * inner];
        let scaled;
        let ps = match &side.sigma {
            Some(sig) => {
                let mut x = p.to_vec();
                scale_columns(&mut x, sig);
                scaled = x;
                &scaled[..]
            }
            None => p,
        };
        for h in 0..HEADS {
            mm_views(
                rm_mut(&mut o, rows, inner).subcols_mut(h * dh, dh),
                cm(ps, N, hr).subcols(h * rows, rows).transpose(),
                cm(pv, N, inner).subcols(h * dh, dh),
                false,
            );
        }
        if side.m > 0 {
            let mut g = vec![0f32; hr * side.m];
            mm_views(
                rm_mut(&mut g, hr, side.m),
                cm(p, N, hr).transpose(),
                cm(&side.e, N, side.m),
                false,
            );
            let mut bw = vec![0f32; side.m * inner];
            mm(&mut bw, &side.b, &lin.w, side.m, d, inner, false);
            for h in 0..HEADS {
                mm_views(
                    rm_mut(&mut o, rows, inner).subcols_mut(h * dh, dh),
                    rm(&g, hr, side.m).subrows(h * rows, rows),
                    rm(&bw, side.m, inner).subcols(h * dh, dh),
                    true,
                );
            }
        }
        for row in o.chunks_exact_mut(inner) {
            add_in_place(row, &lin.b);
        }
        o
    }

    /// Layer `l`'s image→token update and LayerNorm on `side`: `X = K_l + A·U + 1·b_oᵀ`
    /// (`a` the attention weights, column-major `N × HEADS·t`; `U` the tokens' values `vv`
    /// through the output projection), `K_{l+1} = diag(s)·X·C·diag(γ) + 1·βᵀ` with `1/s` the
    /// rows' standard deviations from `|X·C|² = σ²·|k0·M_l·C|² + 2σ·E·(k0·M_l·C·Bᵀ) +
    /// E·(B·C·Bᵀ)·Eᵀ` (`ln` = the image's `k0·hmat` and `|k0·M_l·C|²`).
    fn norm_step(
        &self,
        side: &mut Side,
        l: usize,
        a: Vec<f32>,
        vv: Vec<f32>,
        t: usize,
        ln: (&[f32], &[f32]),
    ) {
        let d = self.d;
        let layer = &self.layers[l];
        let att = &layer.i2t;
        let (inner, dh) = (att.inner(), att.head());
        let ht = HEADS * t;
        let mut u = vec![0f32; ht * d];
        for h in 0..HEADS {
            mm_views(
                rm_mut(&mut u, ht, d).subrows_mut(h * t, t),
                rm(&vv, t, inner).subcols(h * dh, dh),
                rm(&att.o.w, inner, d).subrows(h * dh, dh),
                false,
            );
        }
        side.e.extend_from_slice(&a);
        side.e.extend(std::iter::repeat_n(1f32, N));
        side.b.extend_from_slice(&u);
        side.b.extend_from_slice(&att.o.b);
        side.m += ht + 1;
        side.vv.push(vv);
        let m = side.m;
        // the cross terms, block by block in the order of E's columns
        let (hk, n) = ln;
        let width = self.ln[l].width;
        let hm = cm(hk, N, width);
        let mut cross = vec![0f32; N];
        let mut tmp = vec![0f32; N * t];
        let (mut ec, mut hc) = (0, 0);
        for (k, vvk) in side.vv.iter().enumerate() {
            let o = &self.layers[k].i2t;
            let (ik, dk) = (o.inner(), o.head());
            for h in 0..HEADS {
                mm_views(
                    cm_mut(&mut tmp, N, t),
                    hm.subcols(hc + h * dk, dk),
                    rm(vvk, t, ik).subcols(h * dk, dk).transpose(),
                    false,
                );
                for j in 0..t {
                    let c = ec + h * t + j;
                    fma_into(
                        &mut cross,
                        &side.e[c * N..(c + 1) * N],
                        &tmp[j * N..(j + 1) * N],
                    );
                }
            }
            ec += ht;
            hc += ik;
            for _ in 0..if k < l { 2 } else { 1 } {
                fma_into(
                    &mut cross,
                    &side.e[ec * N..(ec + 1) * N],
                    &hk[hc * N..(hc + 1) * N],
                );
                ec += 1;
                hc += 1;
            }
        }
        debug_assert!(ec == m && hc == width);
        // B·C, its Gram matrix and the quadratic term
        let mut bc = std::mem::take(&mut side.b);
        for row in bc.chunks_exact_mut(d) {
            let mu = row.iter().map(|&v| f64::from(v)).sum::<f64>() as f32 / d as f32;
            row.iter_mut().for_each(|v| *v -= mu);
        }
        let mut gram = vec![0f32; m * m];
        mm_views(
            rm_mut(&mut gram, m, m),
            rm(&bc, m, d),
            rm(&bc, m, d).transpose(),
            false,
        );
        // e·G·eᵀ = e·T·eᵀ with T = G's diagonal plus twice its strict upper triangle
        for i in 0..m {
            for j in 0..m {
                gram[i * m + j] *= match i.cmp(&j) {
                    std::cmp::Ordering::Less => 2.0,
                    std::cmp::Ordering::Equal => 1.0,
                    std::cmp::Ordering::Greater => 0.0,
                };
            }
        }
        // a block of rows at a time, so that E·T stays in the cache for the row sums
        const RB: usize = 256;
        let mut eg = vec![0f32; RB * m];
        let mut quad = vec![0f32; N];
        for r0 in (0..N).step_by(RB) {
            faer::linalg::matmul::triangular::matmul(
                cm_mut(&mut eg, RB, m),
                BlockStructure::Rectangular,
                Accum::Replace,
                cm(&side.e, N, m).subrows(r0, RB),
                BlockStructure::Rectangular,
                rm(&gram, m, m),
                BlockStructure::TriangularUpper,
                1.0f32,
                Par::Seq,
            );
            for (c, g) in eg.chunks_exact(RB).enumerate() {
                fma_into(
                    &mut quad[r0..r0 + RB],
                    &side.e[c * N + r0..c * N + r0 + RB],
                    g,
                );
            }
        }
        let eps = f64::from(layer.norm4.eps);
        let s: Vec<f32> = (0..N)
            .map(|r| {
                let sg = side.sigma.as_ref().map_or(1.0, |s| f64::from(s[r]));
                let sq =
                    sg * sg * f64::from(n[r]) + 2.0 * sg * f64::from(cross[r]) + f64::from(quad[r]);
                (1.0 / ((sq / d as f64).max(0.0) + eps).sqrt()) as f32
            })
            .collect();
        // K_{l+1} = diag(s)·X·C·diag(γ) + 1·βᵀ
        scale_columns(&mut side.e, &s);
        side.sigma = Some(match side.sigma.take() {
            Some(mut sg) => {
                mul_in_place(&mut sg, &s);
                sg
            }
            None => s,
        });
        for row in bc.chunks_exact_mut(d) {
            mul_in_place(row, &layer.norm4.g);
        }
        side.b = bc;
        side.e.extend(std::iter::repeat_n(1f32, N));
        side.b.extend_from_slice(&layer.norm4.b);
        side.m += 1;
    }

    /// The low-resolution (`256 × 256`) logits of masks `which` of a decoded prompt, computed
    /// one row of 64 image tokens at a time.
    pub fn low_res(&self, prep: &ImagePrep, dec: &Decoded, which: &[usize]) -> Vec<Vec<f32>> {
        if which.is_empty() {
            return Vec::new();
        }
        let (d, c1, c2) = (self.d, self.c1, self.c2);
        let c4 = 4 * c1;
        let side = &dec.side;
        let m = side.m;
        let ones;
        let sig = match &side.sigma {
            Some(s) => &s[..],
            None => {
                ones = vec![1f32; N];
                &ones[..]
            }
        };
        // K_L·W = diag(σ)·k0·M_L·W + E·(B·W)
        let mut bw = vec![0f32; m * c4];
        mm(&mut bw, &side.b, &self.up1_w, m, d, c4, false);
        let nm = which.len();
        let mut hy = vec![0f32; c2 * nm];
        for (k, &mi) in which.iter().enumerate() {
            for c in 0..c2 {
                hy[c * nm + k] = dec.hyper[mi][c];
            }
        }
        let mut masks = vec![vec![0f32; LOW * LOW]; nm];
        let bt = UP_ROWS * SIDE;
        let mut out = vec![0f32; bt * c4];
        let mut v = vec![0f32; 4 * bt * 4 * c2];
        let mut lg = vec![0f32; 16 * bt * nm];
        for y0 in (0..SIDE).step_by(UP_ROWS) {
            let i0 = y0 * SIDE;
            for (r, row) in out.chunks_exact_mut(c4).enumerate() {
                let i = i0 + r;
                let s = sig[i];
                for ((o, c), b) in row
                    .iter_mut()
                    .zip(&prep.c0[i * c4..(i + 1) * c4])
                    .zip(&self.up1_b)
                {
                    *o = s * c + b;
                }
            }
            if m > 0 {
                mm_views(
                    rm_mut(&mut out, bt, c4),
                    cm(&side.e, N, m).subrows(i0, bt),
                    rm(&bw, m, c4),
                    true,
                );
            }
            // channel LayerNorm and GELU: rows (token, sub-pixel) of c1 channels
            self.ln2d.rows(&mut out);
            gelu_in_place(&mut out);
            // second convolution: (4·bt × c1)·(c1 × 4·c2), bias, GELU
            for row in v.chunks_exact_mut(4 * c2) {
                row.copy_from_slice(&self.up2_b);
            }
            mm(&mut v, &out, &self.up2_w, 4 * bt, c1, 4 * c2, true);
            gelu_in_place(&mut v);
            // the hypernetwork product: (16·bt × c2)·(c2 × masks)
            mm(&mut lg, &v, &hy, 16 * bt, c2, nm, false);
            // row (token (y, x), s1, s2) → pixel (4y + 2·ky1 + ky2, 4x + 2·kx1 + kx2)
            for r in 0..bt {
                let (y, x) = (y0 + r / SIDE, r % SIDE);
                for s1 in 0..4 {
                    for s2 in 0..4 {
                        let py = 4 * y + 2 * (s1 / 2) + s2 / 2;
                        let px = 4 * x + 2 * (s1 % 2) + s2 % 2;
                        let k = (r * 4 + s1) * 4 + s2;
                        for (j, mk) in masks.iter_mut().enumerate() {
                            mk[py * LOW + px] = lg[k * nm + j];
                        }
                    }
                }
            }
        }
        masks
    }
}

/// A row-major `rows × cols` view.
fn rm(s: &[f32], rows: usize, cols: usize) -> MatRef<'_, f32> {
    MatRef::from_row_major_slice(s, rows, cols)
}

fn rm_mut(s: &mut [f32], rows: usize, cols: usize) -> MatMut<'_, f32> {
    MatMut::from_row_major_slice_mut(s, rows, cols)
}

/// A column-major `rows × cols` view.
fn cm(s: &[f32], rows: usize, cols: usize) -> MatRef<'_, f32> {
    MatRef::from_column_major_slice(s, rows, cols)
}

fn cm_mut(s: &mut [f32], rows: usize, cols: usize) -> MatMut<'_, f32> {
    MatMut::from_column_major_slice_mut(s, rows, cols)
}

/// `a (m×k) · b (k×n)` in `f64`, row-major (the weights' frames, once per model).
fn mul64(a: &[f64], b: &[f64], m: usize, k: usize, n: usize) -> Vec<f64> {
    let mut c = vec![0f64; m * n];
    faer::linalg::matmul::matmul(
        MatMut::from_row_major_slice_mut(&mut c, m, n),
        Accum::Replace,
        MatRef::from_row_major_slice(a, m, k),
        MatRef::from_row_major_slice(b, k, n),
        1.0f64,
        Par::Seq,
    );
    c
}

fn to64(v: &[f32]) -> Vec<f64> {
    v.iter().map(|&x| f64::from(x)).collect()
}

fn to32(v: &[f64]) -> Vec<f32> {
    v.iter().map(|&x| x as f32).collect()
}

/// SAM's random Fourier features (`gauss`: `2 × d/2`) of a point in `[−1, 1]²`.
fn fourier_features(gauss: &[f32], c: [f32; 2], out: &mut [f32]) {
    let h = gauss.len() / 2;
    for k in 0..h {
        let f = 2.0 * std::f32::consts::PI * (c[0] * gauss[k] + c[1] * gauss[h + k]);
        out[k] = f.sin();
        out[h + k] = f.cos();
    }
}

fn plus(a: &[f32], b: &[f32]) -> Vec<f32> {
    a.iter().zip(b).map(|(x, y)| x + y).collect()
}

/// `acc += a ⊙ b`.
fn fma_into(acc: &mut [f32], a: &[f32], b: &[f32]) {
    simd(
        #[inline(always)]
        || {
            for ((x, y), z) in acc.iter_mut().zip(a).zip(b) {
                *x += y * z;
            }
        },
    )
}

fn mul_in_place(a: &mut [f32], b: &[f32]) {
    simd(
        #[inline(always)]
        || {
            for (x, y) in a.iter_mut().zip(b) {
                *x *= y;
            }
        },
    )
}

/// Each `N`-long column of a column-major matrix times `s` elementwise.
fn scale_columns(x: &mut [f32], s: &[f32]) {
    for col in x.chunks_exact_mut(N) {
        mul_in_place(col, s);
    }
}

/// Softmax down each `N`-long column of a column-major matrix.
fn softmax_columns(s: &mut [f32]) {
    simd(
        #[inline(always)]
        || {
            for col in s.chunks_exact_mut(N) {
                let m = max8(col);
                col.iter_mut().for_each(|v| *v = exp_neg(*v - m));
                let inv = 1.0 / sum8(col, |v| v);
                col.iter_mut().for_each(|v| *v *= inv);
            }
        },
    )
}

/// Softmax over each head's `t` columns, row by row, of a column-major `N × HEADS·t`
/// matrix.
fn softmax_heads(s: &mut [f32], t: usize) {
    simd(
        #[inline(always)]
        || {
            let mut mx = vec![0f32; N];
            let mut sum = vec![0f32; N];
            for head in s.chunks_exact_mut(N * t) {
                mx.copy_from_slice(&head[..N]);
                for col in head.chunks_exact(N).skip(1) {
                    for (m, &v) in mx.iter_mut().zip(col) {
                        *m = m.max(v);
                    }
                }
                sum.iter_mut().for_each(|v| *v = 0.0);
                for col in head.chunks_exact_mut(N) {
                    for ((v, &m), z) in col.iter_mut().zip(&mx).zip(sum.iter_mut()) {
                        *v = exp_neg(*v - m);
                        *z += *v;
                    }
                }
                sum.iter_mut().for_each(|v| *v = 1.0 / *v);
                for col in head.chunks_exact_mut(N) {
                    mul_in_place(col, &sum);
                }
            }
        },
    )
}

/// The largest value of a row in eight interleaved lanes (vectorises).
#[inline(always)]
fn max8(row: &[f32]) -> f32 {
    let mut acc = [f32::NEG_INFINITY; 8];
    let chunks = row.chunks_exact(8);
    let rest = chunks
        .remainder()
        .iter()
        .fold(f32::NEG_INFINITY, |m, &v| m.max(v));
    for c in chunks {
        for k in 0..8 {
            acc[k] = acc[k].max(c[k]);
        }
    }
    acc.iter().fold(rest, |m, &v| m.max(v))
}

/// Multi-head attention among the `t` tokens.
fn self_attention(att: &Attn, q: &[f32], k: &[f32], v: &[f32], t: usize) -> Vec<f32> {
    let (inner, dh) = (att.inner(), att.head());
    let scale = 1.0 / (dh as f32).sqrt();
    let (qp, kp, vp) = (att.q.apply(q, t), att.k.apply(k, t), att.v.apply(v, t));
    let mut o = vec![0f32; t * inner];
    let mut s = vec![0f32; t];
    for h in 0..HEADS {
        for i in 0..t {
            for j in 0..t {
                s[j] = (0..dh)
                    .map(|c| qp[i * inner + h * dh + c] * kp[j * inner + h * dh + c])
                    .sum::<f32>()
                    * scale;
            }
            let m = s.iter().copied().fold(f32::NEG_INFINITY, f32::max);
            s.iter_mut().for_each(|x| *x = exp_neg(*x - m));
            let z: f32 = s.iter().sum();
            for c in 0..dh {
                o[i * inner + h * dh + c] = (0..t)
                    .map(|j| s[j] * vp[j * inner + h * dh + c])
                    .sum::<f32>()
                    / z;
            }
        }
    }
    att.o.apply(&o, t)
}

/// An MLP with ReLU between its layers, on one row.
fn mlp(layers: &[Linear], x: &[f32]) -> Vec<f32> {
    let mut h = x.to_vec();
    for (i, l) in layers.iter().enumerate() {
        h = l.apply(&h, 1);
        if i + 1 < layers.len() {
            h.iter_mut().for_each(|v| *v = v.max(0.0));
        }
    }
    h
}

#[inline(always)]
fn add_in_place(a: &mut [f32], b: &[f32]) {
    for (x, y) in a.iter_mut().zip(b) {
        *x += y;
    }
}
