//! SAM's prompt encoder and mask decoder computed here from the export's own weights, with the
//! work that does not depend on the prompt done once per image and the low-rank structure of
//! the two-way transformer used instead of repeating the image side per prompt.
//!
//! What SAM's decoder does per prompt (segment-anything `MaskDecoder.predict_masks`,
//! `TwoWayTransformer`): `T = 5 + points` tokens attend to the 64×64 = 4096 image tokens and the
//! image tokens attend back, twice; the image tokens are then upscaled (two 2×2 transposed
//! convolutions with a channel LayerNorm and GELUs) and dotted with one hypernetwork vector per
//! mask. The export repeats that image side for every prompt (≈ 1.8 GMAC). Here:
//! - the first layer's projections of the image tokens (keys and values of the token→image
//!   attention, queries of the image→token attention) are computed once per image;
//! - an image→token attention's output for image token `i` is `Σ_{h,j} a_hij·U_hj + b` with
//!   `U_hj` = token `j`'s head-`h` value through the head's rows of the output projection: one
//!   `(N × 8T)·(8T × 256)` product instead of two `N × 256 × 128` ones;
//! - a token→image attention of a later layer scores `(keys + pe)·R` with `R = W_k,h·q_hj`
//!   and takes its values as `(Σ_i p_hji·keys_i)·W_v,h` (the softmax weights sum to 1), never
//!   projecting the 4096 image tokens;
//! - the first transposed convolution of the final image tokens is unrolled through the
//!   LayerNorms: with `x_l = keys_l + A_l·U_l + b_l` and `keys_{l+1} = γ_l ⊙ (x_l − μ_l)/σ_l +
//!   β_l`, `keys_{l+1}·W = (x_l·diag(γ_l)·W − μ_l·γ_l·W)/σ_l + β_l·W`, so `keys_L·W` is the
//!   image's `keys_0·diag(Πγ)·W` (once per image) plus one `(N × 8T)` product per layer;
//! - the upscaling runs only for a prompt with a mask that the caller keeps (its predicted IoU
//!   passes the filter), and the hypernetwork product only for those masks.
//!
//! The result equals the export's up to the rounding of the reassociated sums; `Segmenter`
//! compares the two on a probe before it uses this path, and keeps ONNX Runtime when they
//! differ (an export of another architecture, or weights it cannot find by name).
//!
//! Weights are found by the names `torch.onnx.export` keeps (`mask_decoder.…bias`,
//! `…norm1.weight`, `prompt_encoder.…`); a linear layer's folded weight is the initializer of
//! the `MatMul` whose output its bias is added to.
use std::collections::HashMap;

use faer::{Accum, MatMut, MatRef, Par};

use crate::fastmath::{exp_neg, gelu_in_place, simd, softmax_groups};
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
        self.rows_with_stats(x, None);
    }

    /// [`Norm::rows`], also giving each row's mean and `1/σ`.
    fn rows_with_stats(&self, x: &mut [f32], mut out: Option<(&mut [f32], &mut [f32])>) {
        let w = self.g.len();
        simd(
            #[inline(always)]
            || {
                for (i, row) in x.chunks_exact_mut(w).enumerate() {
                    let (mu, s) = stats(row, self.eps);
                    if let Some((m, si)) = out.as_mut() {
                        m[i] = mu;
                        si[i] = s;
                    }
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

/// The weights-only terms of the upscaling's unrolled first convolution for one layer `l`:
/// `W_l' = diag(γ_l ⋯ γ_{L−1})·W`, `b_l·W_l'`, `1·W_l'` and `β_l·W_{l+1}'`.
#[derive(Debug, Clone)]
struct Unroll {
    w: Vec<f32>,
    bias_w: Vec<f32>,
    ones_w: Vec<f32>,
    beta_w: Vec<f32>,
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
    /// The image positional encoding, `N × d`.
    image_pe: Vec<f32>,
    /// First transposed convolution as `d × 4·c1`, column `s·c1 + c` (`s = 2·ky + kx`).
    up1_b: Vec<f32>,
    c1: usize,
    ln2d: Norm,
    /// Second transposed convolution as `c1 × 4·c2`, column `s·c2 + c`.
    up2_w: Vec<f32>,
    up2_b: Vec<f32>,
    c2: usize,
    unroll: Vec<Unroll>,
    hyper: Vec<Vec<Linear>>,
    iou_head: Vec<Linear>,
}

/// What one image gives every prompt.
pub struct ImagePrep {
    k0: Vec<f32>,
    /// First layer: token→image keys and values, image→token queries (`N × inner`).
    kt: Vec<f32>,
    vt: Vec<f32>,
    qi: Vec<f32>,
    /// `keys_0·W_0'` of the unrolled first convolution, `N × 4·c1`.
    c0: Vec<f32>,
}

/// One layer's image→token attention, kept for the upscaling.
struct LayerTrace {
    a: Vec<f32>,
    u: Vec<f32>,
    mu: Vec<f32>,
    s: Vec<f32>,
}

/// A decoded prompt: the predicted IoU of each mask and what the upscaling needs.
pub struct Decoded {
    pub iou: Vec<f32>,
    hyper: Vec<Vec<f32>>,
    traces: Vec<LayerTrace>,
    ht: usize,
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
        // the unrolled first convolution: W_l' = diag(γ_l ⋯ γ_{L−1})·W
        let nl = layers.len();
        let c4 = 4 * c1;
        let mut wl = vec![up1_w.clone(); nl + 1];
        for l in (0..nl).rev() {
            let g = &layers[l].norm4.g;
            for i in 0..d {
                for k in 0..c4 {
                    wl[l][i * c4 + k] = g[i] * wl[l + 1][i * c4 + k];
                }
            }
        }
        let vec_mat = |v: &[f32], m: &[f32]| {
            let mut out = vec![0f64; c4];
            for (i, &vi) in v.iter().enumerate() {
                for k in 0..c4 {
                    out[k] += f64::from(vi) * f64::from(m[i * c4 + k]);
                }
            }
            out.into_iter().map(|x| x as f32).collect::<Vec<f32>>()
        };
        let ones = vec![1f32; d];
        let unroll = (0..nl)
            .map(|l| Unroll {
                bias_w: vec_mat(&layers[l].i2t.o.b, &wl[l]),
                ones_w: vec_mat(&ones, &wl[l]),
                beta_w: vec_mat(&layers[l].norm4.b, &wl[l + 1]),
                w: wl[l].clone(),
            })
            .collect();
        let mut dec = SamDecoder {
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
            image_pe: Vec::new(),
            up1_b,
            c1,
            ln2d,
            up2_w,
            up2_b,
            c2,
            unroll,
            hyper,
            iou_head,
        };
        // the image's positional encoding: the Fourier features of the token centres
        let mut pe = vec![0f32; N * d];
        for y in 0..SIDE {
            for x in 0..SIDE {
                let c = [
                    ((x as f32 + 0.5) / SIDE as f32) * 2.0 - 1.0,
                    ((y as f32 + 0.5) / SIDE as f32) * 2.0 - 1.0,
                ];
                dec.fourier(c, &mut pe[(y * SIDE + x) * d..(y * SIDE + x + 1) * d]);
            }
        }
        dec.image_pe = pe;
        Ok(dec)
    }

    /// Masks per prompt.
    pub fn masks(&self) -> usize {
        self.masks
    }

    /// SAM's random Fourier features of a point in `[−1, 1]²`.
    fn fourier(&self, c: [f32; 2], out: &mut [f32]) {
        let h = self.d / 2;
        for k in 0..h {
            let f = 2.0 * std::f32::consts::PI * (c[0] * self.gauss[k] + c[1] * self.gauss[h + k]);
            out[k] = f.sin();
            out[h + k] = f.cos();
        }
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
        let kp0: Vec<f32> = k0.iter().zip(&self.image_pe).map(|(a, b)| a + b).collect();
        let l0 = &self.layers[0];
        let kt = l0.t2i.k.apply(&kp0, N);
        let vt = l0.t2i.v.apply(&k0, N);
        let qi = l0.i2t.q.apply(&kp0, N);
        let c4 = 4 * self.c1;
        let mut c0 = vec![0f32; N * c4];
        mm(&mut c0, &k0, &self.unroll[0].w, N, d, c4, false);
        ImagePrep { k0, kt, vt, qi, c0 }
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
        let mut keys: Option<Vec<f32>> = None; // keys_l for l ≥ 1
        let mut kp: Option<Vec<f32>> = None;
        let mut traces = Vec::with_capacity(self.layers.len());
        for (l, layer) in self.layers.iter().enumerate() {
            // self-attention (the first layer without positional terms or residual)
            if l == 0 {
                q = self_attention(&layer.self_attn, &q, &q, &q, t);
            } else {
                let qq: Vec<f32> = q.iter().zip(&tok).map(|(a, b)| a + b).collect();
                let a = self_attention(&layer.self_attn, &qq, &qq, &q, t);
                add_in_place(&mut q, &a);
            }
            layer.norm1.rows(&mut q);
            // token → image
            let qq: Vec<f32> = q.iter().zip(&tok).map(|(a, b)| a + b).collect();
            let a = match (&keys, &kp) {
                (Some(k), Some(kp)) => self.token_to_image(&layer.t2i, &qq, t, t, k, kp),
                _ => token_to_image_first(&layer.t2i, &qq, t, &prep.kt, &prep.vt),
            };
            add_in_place(&mut q, &a);
            layer.norm2.rows(&mut q);
            // MLP
            let mut h = layer.mlp1.apply(&q, t);
            h.iter_mut().for_each(|v| *v = v.max(0.0));
            let m = layer.mlp2.apply(&h, t);
            add_in_place(&mut q, &m);
            layer.norm3.rows(&mut q);
            // image → token
            let qq: Vec<f32> = q.iter().zip(&tok).map(|(a, b)| a + b).collect();
            let att = &layer.i2t;
            let (inner, dh) = (att.inner(), att.head());
            let kk = att.k.apply(&qq, t);
            let vv = att.v.apply(&q, t);
            let ht = HEADS * t;
            let scale = 1.0 / (dh as f32).sqrt();
            let mut a = vec![0f32; N * ht];
            match &kp {
                None => {
                    // per head: qi_h (N × dh) · kk_hᵀ (dh × t)
                    for h in 0..HEADS {
                        mm_views(
                            MatMut::from_row_major_slice_mut(&mut a, N, ht).subcols_mut(h * t, t),
                            MatRef::from_row_major_slice(&prep.qi, N, inner).subcols(h * dh, dh),
                            MatRef::from_row_major_slice(&kk, t, inner)
                                .subcols(h * dh, dh)
                                .transpose(),
                            false,
                        );
                    }
                    a.iter_mut().for_each(|v| *v *= scale);
                }
                Some(kp) => {
                    // (keys + pe)·R with R = W_q,h·kk_hᵀ, plus b_q,h·kk_h
                    let (r, rb) = fold_query_side(&att.q, &kk, t, scale);
                    for row in a.chunks_exact_mut(ht) {
                        row.copy_from_slice(&rb);
                    }
                    mm(&mut a, kp, &r, N, d, ht, true);
                }
            }
            // softmax over the t tokens of each head
            softmax_groups(&mut a, t);
            // U_hj = vv_hj · W_o[h rows]
            let mut u = vec![0f32; ht * d];
            for h in 0..HEADS {
                mm_views(
                    MatMut::from_row_major_slice_mut(&mut u, ht, d).subrows_mut(h * t, t),
                    MatRef::from_row_major_slice(&vv, t, inner).subcols(h * dh, dh),
                    MatRef::from_row_major_slice(&att.o.w, inner, d).subrows(h * dh, dh),
                    false,
                );
            }
            // x = keys + A·U + b_o, LayerNorm → keys_{l+1}
            let mut x = match keys.take() {
                Some(k) => k,
                None => prep.k0.clone(),
            };
            simd(
                #[inline(always)]
                || {
                    for row in x.chunks_exact_mut(d) {
                        add_in_place(row, &att.o.b);
                    }
                },
            );
            mm(&mut x, &a, &u, N, ht, d, true);
            let mut mu = vec![0f32; N];
            let mut s = vec![0f32; N];
            layer.norm4.rows_with_stats(&mut x, Some((&mut mu, &mut s)));
            let mut p = kp.take().unwrap_or_else(|| vec![0f32; N * d]);
            simd(
                #[inline(always)]
                || {
                    for ((o, a), b) in p.iter_mut().zip(&x).zip(&self.image_pe) {
                        *o = a + b;
                    }
                },
            );
            keys = Some(x);
            kp = Some(p);
            traces.push(LayerTrace { a, u, mu, s });
        }
        // final token → image attention, for the output tokens only
        let to = 1 + self.masks;
        let qq: Vec<f32> = q[..to * d].iter().zip(&tok).map(|(a, b)| a + b).collect();
        let (k, p) = (keys.expect("one layer"), kp.expect("one layer"));
        let a = self.token_to_image(&self.final_attn, &qq, to, to, &k, &p);
        let mut out = q[..to * d].to_vec();
        add_in_place(&mut out, &a);
        self.norm_final.rows(&mut out);
        let iou = mlp(&self.iou_head, &out[..d]);
        let hyper = (0..self.masks)
            .map(|m| mlp(&self.hyper[m], &out[(1 + m) * d..(2 + m) * d]))
            .collect();
        Decoded {
            iou,
            hyper,
            traces,
            ht: HEADS * t,
        }
    }

    /// Token→image attention of a later layer on materialised keys: scores `(keys + pe)·R`,
    /// values `(Σ_i p_i·keys_i)·W_v,h + b_v,h`; returns the output projection, `rows × d`.
    fn token_to_image(
        &self,
        att: &Attn,
        qq: &[f32],
        rows: usize,
        t: usize,
        keys: &[f32],
        kp: &[f32],
    ) -> Vec<f32> {
        let d = self.d;
        let (inner, dh) = (att.inner(), att.head());
        let scale = 1.0 / (dh as f32).sqrt();
        let qp = att.q.apply(qq, rows);
        let (r, rb) = fold_query_side(&att.k, &qp, t, scale);
        let ht = HEADS * t;
        let mut s = vec![0f32; N * ht];
        for row in s.chunks_exact_mut(ht) {
            row.copy_from_slice(&rb);
        }
        mm(&mut s, kp, &r, N, d, ht, true);
        softmax_columns(&mut s, ht);
        // Σ_i p_hji keys_i : (ht × N)·(N × d)
        let mut pk = vec![0f32; ht * d];
        mm_views(
            MatMut::from_row_major_slice_mut(&mut pk, ht, d),
            MatRef::from_row_major_slice(&s, N, ht).transpose(),
            MatRef::from_row_major_slice(keys, N, d),
            false,
        );
        let mut o = vec![0f32; rows * inner];
        for h in 0..HEADS {
            for j in 0..rows {
                let dst = &mut o[j * inner + h * dh..j * inner + (h + 1) * dh];
                dst.copy_from_slice(&att.v.b[h * dh..(h + 1) * dh]);
            }
            mm_views(
                MatMut::from_row_major_slice_mut(&mut o, rows, inner).subcols_mut(h * dh, dh),
                MatRef::from_row_major_slice(&pk, ht, d).subrows(h * t, rows),
                MatRef::from_row_major_slice(&att.v.w, d, inner).subcols(h * dh, dh),
                true,
            );
        }
        att.o.apply(&o, rows)
    }

    /// The low-resolution (`256 × 256`) logits of masks `which` of a decoded prompt.
    pub fn low_res(&self, prep: &ImagePrep, dec: &Decoded, which: &[usize]) -> Vec<Vec<f32>> {
        if which.is_empty() {
            return Vec::new();
        }
        let (c1, c2) = (self.c1, self.c2);
        let c4 = 4 * c1;
        // keys_L·W through the LayerNorms (module docs)
        let mut out = prep.c0.clone();
        let mut tmp = vec![0f32; N * c4];
        let mut uw = vec![0f32; dec.ht * c4];
        for (tr, un) in dec.traces.iter().zip(&self.unroll) {
            mm(&mut uw, &tr.u, &un.w, dec.ht, self.d, c4, false);
            mm(&mut tmp, &tr.a, &uw, N, dec.ht, c4, false);
            simd(
                #[inline(always)]
                || {
                    for i in 0..N {
                        let (mu, s) = (tr.mu[i], tr.s[i]);
                        let o = &mut out[i * c4..(i + 1) * c4];
                        let t = &tmp[i * c4..(i + 1) * c4];
                        for k in 0..c4 {
                            o[k] =
                                s * (o[k] + t[k] + un.bias_w[k] - mu * un.ones_w[k]) + un.beta_w[k];
                        }
                    }
                },
            );
        }
        // bias, channel LayerNorm, GELU: rows (token, sub-pixel) of c1 channels
        simd(
            #[inline(always)]
            || {
                for row in out.chunks_exact_mut(c4) {
                    add_in_place(row, &self.up1_b);
                }
            },
        );
        self.ln2d.rows(&mut out);
        gelu_in_place(&mut out);
        // second convolution: (4N × c1)·(c1 × 4·c2), bias, GELU
        let rows = 4 * N;
        let mut v = vec![0f32; rows * 4 * c2];
        for row in v.chunks_exact_mut(4 * c2) {
            row.copy_from_slice(&self.up2_b);
        }
        mm(&mut v, &out, &self.up2_w, rows, c1, 4 * c2, true);
        gelu_in_place(&mut v);
        // the hypernetwork product: (16N × c2)·(c2 × masks)
        let nm = which.len();
        let mut hy = vec![0f32; c2 * nm];
        for (k, &m) in which.iter().enumerate() {
            for c in 0..c2 {
                hy[c * nm + k] = dec.hyper[m][c];
            }
        }
        let mut lg = vec![0f32; 16 * N * nm];
        mm(&mut lg, &v, &hy, 16 * N, c2, nm, false);
        // row (token i, s1, s2) → pixel (4y + 2·ky1 + ky2, 4x + 2·kx1 + kx2)
        let mut masks = vec![vec![0f32; LOW * LOW]; nm];
        for i in 0..N {
            let (y, x) = (i / SIDE, i % SIDE);
            for s1 in 0..4 {
                for s2 in 0..4 {
                    let py = 4 * y + 2 * (s1 / 2) + s2 / 2;
                    let px = 4 * x + 2 * (s1 % 2) + s2 % 2;
                    let r = (i * 4 + s1) * 4 + s2;
                    for (k, m) in masks.iter_mut().enumerate() {
                        m[py * LOW + px] = lg[r * nm + k];
                    }
                }
            }
        }
        masks
    }
}

/// `R = W_h·pᵀ_h` per head (`din × HEADS·t`, column `h·t + j`) and `b_h·p_hj`, both scaled:
/// a projection `W` applied to the image side, folded into the scores against the
/// per-prompt projected tokens `p` (`t × inner`).
fn fold_query_side(lin: &Linear, p: &[f32], t: usize, scale: f32) -> (Vec<f32>, Vec<f32>) {
    let (din, inner) = (lin.din, lin.dout);
    let dh = inner / HEADS;
    let ht = HEADS * t;
    let mut r = vec![0f32; din * ht];
    for h in 0..HEADS {
        mm_views(
            MatMut::from_row_major_slice_mut(&mut r, din, ht).subcols_mut(h * t, t),
            MatRef::from_row_major_slice(&lin.w, din, inner).subcols(h * dh, dh),
            MatRef::from_row_major_slice(p, p.len() / inner, inner)
                .subrows(0, t)
                .subcols(h * dh, dh)
                .transpose(),
            false,
        );
    }
    r.iter_mut().for_each(|v| *v *= scale);
    let mut rb = vec![0f32; ht];
    for h in 0..HEADS {
        for j in 0..t {
            let s: f32 = (0..dh)
                .map(|c| lin.b[h * dh + c] * p[j * inner + h * dh + c])
                .sum();
            rb[h * t + j] = s * scale;
        }
    }
    (r, rb)
}

/// Softmax down each column of an `N × cols` row-major matrix.
fn softmax_columns(s: &mut [f32], cols: usize) {
    simd(
        #[inline(always)]
        || softmax_columns_inner(s, cols),
    )
}

#[inline(always)]
fn softmax_columns_inner(s: &mut [f32], cols: usize) {
    let mut mx = vec![f32::NEG_INFINITY; cols];
    for row in s.chunks_exact(cols) {
        for (m, &v) in mx.iter_mut().zip(row) {
            *m = m.max(v);
        }
    }
    let mut sum = vec![0f32; cols];
    for row in s.chunks_exact_mut(cols) {
        for ((v, &m), acc) in row.iter_mut().zip(&mx).zip(sum.iter_mut()) {
            *v = exp_neg(*v - m);
            *acc += *v;
        }
    }
    let inv: Vec<f32> = sum.iter().map(|&x| 1.0 / x).collect();
    for row in s.chunks_exact_mut(cols) {
        for (v, &k) in row.iter_mut().zip(&inv) {
            *v *= k;
        }
    }
}

/// The first layer's token→image attention on the image's precomputed keys and values.
fn token_to_image_first(att: &Attn, qq: &[f32], t: usize, kt: &[f32], vt: &[f32]) -> Vec<f32> {
    let (inner, dh) = (att.inner(), att.head());
    let scale = 1.0 / (dh as f32).sqrt();
    let qp = att.q.apply(qq, t);
    let ht = HEADS * t;
    let mut s = vec![0f32; N * ht];
    for h in 0..HEADS {
        mm_views(
            MatMut::from_row_major_slice_mut(&mut s, N, ht).subcols_mut(h * t, t),
            MatRef::from_row_major_slice(kt, N, inner).subcols(h * dh, dh),
            MatRef::from_row_major_slice(&qp, t, inner)
                .subcols(h * dh, dh)
                .transpose(),
            false,
        );
    }
    s.iter_mut().for_each(|v| *v *= scale);
    softmax_columns(&mut s, ht);
    let mut o = vec![0f32; t * inner];
    for h in 0..HEADS {
        mm_views(
            MatMut::from_row_major_slice_mut(&mut o, t, inner).subcols_mut(h * dh, dh),
            MatRef::from_row_major_slice(&s, N, ht)
                .subcols(h * t, t)
                .transpose(),
            MatRef::from_row_major_slice(vt, N, inner).subcols(h * dh, dh),
            false,
        );
    }
    att.o.apply(&o, t)
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
