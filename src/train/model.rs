//! The learnable part of identity training and its losses, generic over `f32` (training) and
//! `f64` (the gradient check).
//!
//! * Parameters: one code `e_i ∈ R^D` per Gaussian and a linear classifier `(W, b)` over `C`
//!   classes (class 0 = background / no label, classes `1..C` = the label ids that occur in the
//!   training maps).
//! * A rendered code is `E(p) = Σ_{i ∈ list(p)} w_i e_i` over a pixel's cached contribution list
//!   (geometry is frozen, so the `w_i` are constants): the forward pass is a sparse product and
//!   the backward pass scatters `w_i · ∂L/∂E(p)` back into the codes.
//! * Both losses are evaluated over an [`Active`] set of classes: in exact mode every class; in
//!   sampled mode the classes that matter for the batch (the labels present in the view, the
//!   background) plus `s` negatives drawn uniformly from the rest, each standing for
//!   `ω = |rest| / s` classes. The log-partition `log(Σ_active e^z + ω Σ_neg e^z)` estimates the
//!   full one (the sum over the rest is unbiased; its log is consistent), so the cost per pixel
//!   does not grow with the number of labels `K`.
//! * Work is split into chunks of fixed size whose partial sums are added in chunk order, so
//!   results do not depend on the number of threads.
use ndarray::{Array2, Axis};
use rayon::prelude::*;

pub use super::kl::knn_kl;

/// Rows per parallel chunk (fixed: results must not depend on the thread count).
pub const CHUNK: usize = 256;

/// The scalar type of a model: `f32` for training, `f64` for gradient checks.
pub trait Real:
    num_traits::Float
    + ndarray::LinalgScalar
    + std::iter::Sum
    + std::ops::AddAssign
    + Send
    + Sync
    + std::fmt::Debug
    + 'static
{
    fn of(x: f64) -> Self;
    fn f64(self) -> f64;
}

impl Real for f32 {
    fn of(x: f64) -> Self {
        x as f32
    }
    fn f64(self) -> f64 {
        f64::from(self)
    }
}

impl Real for f64 {
    fn of(x: f64) -> Self {
        x
    }
    fn f64(self) -> f64 {
        self
    }
}

/// Codes and classifier.
#[derive(Debug, Clone, PartialEq)]
pub struct Model<T> {
    pub dim: usize,
    /// `N × D`, row-major.
    pub codes: Vec<T>,
    /// `C × D`.
    pub weights: Array2<T>,
    /// `C`.
    pub bias: Vec<T>,
}

impl<T: Real> Model<T> {
    /// Number of Gaussians.
    pub fn gaussians(&self) -> usize {
        self.codes.len() / self.dim.max(1)
    }

    /// Number of classes (background included).
    pub fn classes(&self) -> usize {
        self.bias.len()
    }

    /// Gaussian `g`'s code.
    pub fn code(&self, g: usize) -> &[T] {
        &self.codes[g * self.dim..(g + 1) * self.dim]
    }

    /// The same model in another scalar type.
    pub fn cast<U: Real>(&self) -> Model<U> {
        Model {
            dim: self.dim,
            codes: self.codes.iter().map(|x| U::of(x.f64())).collect(),
            weights: self.weights.mapv(|x| U::of(x.f64())),
            bias: self.bias.iter().map(|x| U::of(x.f64())).collect(),
        }
    }
}

/// The classes a loss is evaluated over (see the module docs).
#[derive(Debug, Clone, PartialEq)]
pub struct Active {
    /// Classes evaluated exactly (sorted, unique).
    pub members: Vec<u32>,
    /// Sampled stand-ins for the other classes (disjoint from `members`).
    pub negatives: Vec<u32>,
    /// `ln ω`: each negative stands for `ω` classes.
    pub log_omega: f64,
}

impl Active {
    /// Every one of `classes` classes, exactly.
    pub fn full(classes: usize) -> Active {
        Active {
            members: (0..classes as u32).collect(),
            negatives: Vec::new(),
            log_omega: 0.0,
        }
    }

    /// `members` exactly and `s` negatives drawn uniformly (without replacement) from the
    /// other classes; all of them when `s` ≥ their number.
    pub fn sampled<R: rand::Rng>(
        classes: usize,
        mut members: Vec<u32>,
        s: usize,
        rng: &mut R,
    ) -> Active {
        members.sort_unstable();
        members.dedup();
        let mut is_member = vec![false; classes];
        for &m in &members {
            is_member[m as usize] = true;
        }
        let rest: Vec<u32> = (0..classes as u32)
            .filter(|&c| !is_member[c as usize])
            .collect();
        if s >= rest.len() {
            return Active {
                members,
                negatives: rest,
                log_omega: 0.0,
            };
        }
        let mut idx = rand::seq::index::sample(rng, rest.len(), s).into_vec();
        idx.sort_unstable();
        let negatives: Vec<u32> = idx.into_iter().map(|i| rest[i]).collect();
        Active {
            log_omega: (rest.len() as f64 / s as f64).ln(),
            members,
            negatives,
        }
    }

    /// `members` exactly, and as negatives the classes of `sample` that are not members, where
    /// `sample` was drawn uniformly without replacement from all `classes` classes (so its
    /// non-members are a uniform sample of the rest).
    pub fn from_sample(classes: usize, mut members: Vec<u32>, sample: &[u32]) -> Active {
        members.sort_unstable();
        members.dedup();
        let negatives: Vec<u32> = sample
            .iter()
            .copied()
            .filter(|c| members.binary_search(c).is_err())
            .collect();
        let rest = classes - members.len();
        let log_omega = if negatives.is_empty() {
            0.0
        } else {
            (rest as f64 / negatives.len() as f64).ln()
        };
        Active {
            members,
            negatives,
            log_omega,
        }
    }

    /// Columns: members, then negatives.
    pub fn columns(&self) -> impl Iterator<Item = u32> + '_ {
        self.members.iter().chain(&self.negatives).copied()
    }

    /// Number of columns.
    pub fn len(&self) -> usize {
        self.members.len() + self.negatives.len()
    }

    /// Whether there is no column.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The column of class `c` among the members.
    pub fn member_column(&self, c: u32) -> Option<usize> {
        self.members.binary_search(&c).ok()
    }

    /// `(W_U, b̃_U)`: the active rows of the classifier, with `ln ω` added to the negatives'
    /// biases (so `logsumexp` of a row's logits is the estimated log-partition).
    pub(super) fn gather<T: Real>(&self, m: &Model<T>) -> (Array2<T>, Vec<T>) {
        let mut w = Array2::zeros((self.len(), m.dim));
        let mut b = Vec::with_capacity(self.len());
        let lo = T::of(self.log_omega);
        for (j, c) in self.columns().enumerate() {
            w.row_mut(j).assign(&m.weights.row(c as usize));
            b.push(
                m.bias[c as usize]
                    + if j >= self.members.len() {
                        lo
                    } else {
                        T::zero()
                    },
            );
        }
        (w, b)
    }
}

/// Gradients, kept sparse by row: the touched code rows and classifier rows are listed.
#[derive(Debug, Clone)]
pub struct Grads<T> {
    pub dim: usize,
    pub codes: Vec<T>,
    pub weights: Array2<T>,
    pub bias: Vec<T>,
    /// Code rows with a (possibly zero) gradient, in first-touch order.
    pub touched_codes: Vec<u32>,
    /// Classes with a gradient, in first-touch order.
    pub touched_classes: Vec<u32>,
    code_mark: Vec<bool>,
    class_mark: Vec<bool>,
}

impl<T: Real> Grads<T> {
    /// Zero gradients for `m`'s shapes.
    pub fn new(m: &Model<T>) -> Grads<T> {
        Grads {
            dim: m.dim,
            codes: vec![T::zero(); m.codes.len()],
            weights: Array2::zeros(m.weights.dim()),
            bias: vec![T::zero(); m.bias.len()],
            touched_codes: Vec::new(),
            touched_classes: Vec::new(),
            code_mark: vec![false; m.gaussians()],
            class_mark: vec![false; m.classes()],
        }
    }

    /// Adds `v` to Gaussian `g`'s code gradient.
    #[inline]
    pub(super) fn add_code(&mut self, g: u32, scale: T, v: &[T]) {
        let gi = g as usize;
        if !self.code_mark[gi] {
            self.code_mark[gi] = true;
            self.touched_codes.push(g);
        }
        let row = &mut self.codes[gi * self.dim..(gi + 1) * self.dim];
        for (r, &x) in row.iter_mut().zip(v) {
            *r += scale * x;
        }
    }

    /// Adds the active rows' classifier gradient.
    pub(super) fn add_classes(&mut self, active: &Active, dw: &Array2<T>, db: &[T]) {
        for (j, c) in active.columns().enumerate() {
            let ci = c as usize;
            if !self.class_mark[ci] {
                self.class_mark[ci] = true;
                self.touched_classes.push(c);
            }
            let mut row = self.weights.row_mut(ci);
            row += &dw.row(j);
            self.bias[ci] += db[j];
        }
    }

    /// Zeroes the touched rows (after an optimiser step).
    pub fn clear(&mut self) {
        let d = self.dim;
        for &g in &self.touched_codes {
            let gi = g as usize;
            self.codes[gi * d..(gi + 1) * d].fill(T::zero());
            self.code_mark[gi] = false;
        }
        for &c in &self.touched_classes {
            self.weights.row_mut(c as usize).fill(T::zero());
            self.bias[c as usize] = T::zero();
            self.class_mark[c as usize] = false;
        }
        self.touched_codes.clear();
        self.touched_classes.clear();
    }
}

/// A batch of pixels: their contribution lists and target classes.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PixelBatch {
    /// `offsets[r]..offsets[r + 1]` are row `r`'s entries.
    pub offsets: Vec<u32>,
    pub ids: Vec<u32>,
    pub weights: Vec<f32>,
    /// Target class per row.
    pub targets: Vec<u32>,
}

impl PixelBatch {
    /// Number of pixels.
    pub fn len(&self) -> usize {
        self.targets.len()
    }

    /// Whether the batch is empty.
    pub fn is_empty(&self) -> bool {
        self.targets.is_empty()
    }

    /// Appends a pixel.
    pub fn push(&mut self, ids: &[u32], weights: &[f32], target: u32) {
        if self.offsets.is_empty() {
            self.offsets.push(0);
        }
        self.ids.extend_from_slice(ids);
        self.weights.extend_from_slice(weights);
        self.offsets.push(self.ids.len() as u32);
        self.targets.push(target);
    }

    /// Row `r`'s `(ids, weights)`.
    #[inline]
    pub fn row(&self, r: usize) -> (&[u32], &[f32]) {
        let (a, b) = (self.offsets[r] as usize, self.offsets[r + 1] as usize);
        (&self.ids[a..b], &self.weights[a..b])
    }
}

/// Rendered codes `E(p) = Σ w_i e_i` of rows `rows` of a batch.
pub fn render_rows<T: Real>(
    m: &Model<T>,
    b: &PixelBatch,
    rows: std::ops::Range<usize>,
) -> Array2<T> {
    let d = m.dim;
    let mut e = Array2::zeros((rows.len(), d));
    for (r, p) in rows.enumerate() {
        let (ids, ws) = b.row(p);
        let mut out = e.row_mut(r);
        let out = out.as_slice_mut().expect("contiguous row");
        for (&g, &w) in ids.iter().zip(ws) {
            let w = T::of(f64::from(w));
            for (o, &x) in out.iter_mut().zip(m.code(g as usize)) {
                *o += w * x;
            }
        }
    }
    e
}

/// Logits `E·W_Uᵀ + b̃_U` of a block of rows.
pub(super) fn logits<T: Real>(e: &Array2<T>, w: &Array2<T>, b: &[T]) -> Array2<T> {
    let mut z = e.dot(&w.t());
    for mut row in z.rows_mut() {
        for (x, &bb) in row.iter_mut().zip(b) {
            *x += bb;
        }
    }
    z
}

/// `logsumexp` of a slice (−∞ for an empty one).
pub(super) fn lse<T: Real>(z: &[T]) -> T {
    let m = z.iter().copied().fold(T::neg_infinity(), T::max);
    if m == T::neg_infinity() {
        return m;
    }
    m + z.iter().map(|&x| (x - m).exp()).sum::<T>().ln()
}

/// Per-chunk partial results, added in chunk order.
struct Partial<T> {
    loss: f64,
    /// `∂L/∂E` (or `∂L/∂e`) per row of the chunk.
    de: Array2<T>,
    dw: Array2<T>,
    db: Vec<T>,
}

/// Adds `dZ` (already scaled) into the classifier gradient of a chunk and returns `∂L/∂E`.
pub(super) fn backprop<T: Real>(
    dz: &Array2<T>,
    e: &Array2<T>,
    w: &Array2<T>,
) -> (Array2<T>, Array2<T>, Vec<T>) {
    let de = dz.dot(w);
    let dw = dz.t().dot(e);
    let db = dz.sum_axis(Axis(0)).to_vec();
    (de, dw, db)
}

/// Cross-entropy of the batch over `active` (every target must be a member):
/// `scale · Σ_p (log Ẑ(p) − z_target(p))`. Adds its gradient into `g` and returns the loss
/// (already multiplied by `scale`) in `f64`.
pub fn cross_entropy<T: Real>(
    m: &Model<T>,
    batch: &PixelBatch,
    active: &Active,
    scale: f64,
    g: &mut Grads<T>,
) -> f64 {
    cross_entropy_mixed(m, batch, active, &[], 0.0, scale, g)
}

/// The cross-entropy mixed with a group-level one: per pixel
/// `(1 − μ)(log Ẑ − z_t) + μ (log Ẑ − log Σ_{u ∈ G(t)} e^{z_u})`, where `G(t)` are the active
/// columns whose class has the target's group (`group[class]`, the evaluation class of a
/// label, say): the second term asks for the right group, not the right label among its
/// members. `μ = 0` (or an empty `group`) is [`cross_entropy`]. Sampled negatives take part
/// with their `ln ω` (a negative of the target's group stands for `ω` classes of it).
pub fn cross_entropy_mixed<T: Real>(
    m: &Model<T>,
    batch: &PixelBatch,
    active: &Active,
    group: &[u32],
    mu: f64,
    scale: f64,
    g: &mut Grads<T>,
) -> f64 {
    let mu = if group.is_empty() { 0.0 } else { mu };
    let col_group: Vec<u32> = if mu > 0.0 {
        active.columns().map(|c| group[c as usize]).collect()
    } else {
        Vec::new()
    };
    let (w, b) = active.gather(m);
    let cols: Vec<usize> = batch
        .targets
        .iter()
        .map(|&t| {
            active
                .member_column(t)
                .expect("target classes are active members")
        })
        .collect();
    let s = T::of(scale);
    let chunks: Vec<std::ops::Range<usize>> = (0..batch.len())
        .step_by(CHUNK)
        .map(|a| a..(a + CHUNK).min(batch.len()))
        .collect();
    let parts: Vec<Partial<T>> = chunks
        .par_iter()
        .map(|rows| {
            let e = render_rows(m, batch, rows.clone());
            let mut z = logits(&e, &w, &b);
            let mut loss = 0.0;
            for (r, mut row) in z.rows_mut().into_iter().enumerate() {
                let zs = row.as_slice_mut().expect("contiguous");
                let lz = lse(zs);
                let t = cols[rows.start + r];
                if mu > 0.0 {
                    let gt = col_group[t];
                    let lg = lse(&zs
                        .iter()
                        .zip(&col_group)
                        .filter(|(_, g)| **g == gt)
                        .map(|(&z, _)| z)
                        .collect::<Vec<T>>());
                    loss += (1.0 - mu) * (lz - zs[t]).f64() + mu * (lz - lg).f64();
                    let (sl, sg) = (T::of(scale * (1.0 - mu)), T::of(scale * mu));
                    for (u, x) in zs.iter_mut().enumerate() {
                        let q = if col_group[u] == gt {
                            (*x - lg).exp() * sg
                        } else {
                            T::zero()
                        };
                        *x = (*x - lz).exp() * s - q - if u == t { sl } else { T::zero() };
                    }
                } else {
                    loss += (lz - zs[t]).f64();
                    for x in zs.iter_mut() {
                        *x = (*x - lz).exp() * s;
                    }
                    zs[t] = zs[t] - s;
                }
            }
            let (de, dw, db) = backprop(&z, &e, &w);
            Partial { loss, de, dw, db }
        })
        .collect();
    let mut total = 0.0;
    for (rows, p) in chunks.iter().zip(&parts) {
        total += p.loss;
        for (r, pix) in rows.clone().enumerate() {
            let de = p.de.row(r);
            let de = de.as_slice().expect("contiguous");
            let (ids, ws) = batch.row(pix);
            for (&gid, &wt) in ids.iter().zip(ws) {
                g.add_code(gid, T::of(f64::from(wt)), de);
            }
        }
        g.add_classes(active, &p.dw, &p.db);
    }
    total * scale
}

/// Adam with one moment pair and one step count per row, updated only for rows that have a
/// gradient (sparse / lazy Adam: a row not seen in an iteration keeps its state).
#[derive(Debug, Clone)]
pub struct Adam<T> {
    pub lr: f64,
    pub beta1: f64,
    pub beta2: f64,
    pub eps: f64,
    width: usize,
    m: Vec<T>,
    v: Vec<T>,
    t: Vec<u32>,
}

impl<T: Real> Adam<T> {
    /// State for `rows` rows of `width` values.
    pub fn new(rows: usize, width: usize, lr: f64, eps: f64) -> Adam<T> {
        Adam {
            lr,
            beta1: 0.9,
            beta2: 0.999,
            eps,
            width,
            m: vec![T::zero(); rows * width],
            v: vec![T::zero(); rows * width],
            t: vec![0; rows],
        }
    }

    /// One step of row `r`: `param -= lr · m̂ / (√v̂ + ε)`.
    pub fn step(&mut self, r: usize, param: &mut [T], grad: &[T]) {
        let w = self.width;
        self.t[r] += 1;
        let t = self.t[r] as i32;
        let (b1, b2) = (self.beta1, self.beta2);
        let c1 = T::of(1.0 / (1.0 - b1.powi(t)));
        let c2 = T::of(1.0 / (1.0 - b2.powi(t)));
        let (tb1, tb2) = (T::of(b1), T::of(b2));
        let (ob1, ob2) = (T::of(1.0 - b1), T::of(1.0 - b2));
        let (lr, eps) = (T::of(self.lr), T::of(self.eps));
        let m = &mut self.m[r * w..(r + 1) * w];
        let v = &mut self.v[r * w..(r + 1) * w];
        for i in 0..w {
            m[i] = tb1 * m[i] + ob1 * grad[i];
            v[i] = tb2 * v[i] + ob2 * grad[i] * grad[i];
            param[i] = param[i] - lr * (m[i] * c1) / ((v[i] * c2).sqrt() + eps);
        }
    }

    /// Bytes of state.
    pub fn bytes(&self) -> usize {
        (self.m.len() + self.v.len()) * std::mem::size_of::<T>() + self.t.len() * 4
    }
}

/// The optimiser of a model: Adam on the codes and on the classifier rows (weights and bias).
pub struct Optimiser<T> {
    pub codes: Adam<T>,
    pub classifier: Adam<T>,
}

impl<T: Real> Optimiser<T> {
    /// Adam for `m` with learning rates `lr_codes` (ε 1e-15, as the reference) and
    /// `lr_classifier` (ε 1e-8).
    pub fn new(m: &Model<T>, lr_codes: f64, lr_classifier: f64) -> Optimiser<T> {
        Optimiser {
            codes: Adam::new(m.gaussians(), m.dim, lr_codes, 1e-15),
            classifier: Adam::new(m.classes(), m.dim + 1, lr_classifier, 1e-8),
        }
    }

    /// Applies the touched rows of `g` to `m`, then clears `g`.
    pub fn step(&mut self, m: &mut Model<T>, g: &mut Grads<T>) {
        let d = m.dim;
        // In memory order: the rows of four large arrays are visited with fewer cache misses.
        g.touched_codes.sort_unstable();
        for &gid in &g.touched_codes {
            let r = gid as usize;
            self.codes.step(
                r,
                &mut m.codes[r * d..(r + 1) * d],
                &g.codes[r * d..(r + 1) * d],
            );
        }
        let mut p = vec![T::zero(); d + 1];
        let mut gr = vec![T::zero(); d + 1];
        for &c in &g.touched_classes {
            let c = c as usize;
            for (j, (pj, gj)) in p.iter_mut().zip(gr.iter_mut()).take(d).enumerate() {
                *pj = m.weights[[c, j]];
                *gj = g.weights[[c, j]];
            }
            p[d] = m.bias[c];
            gr[d] = g.bias[c];
            self.classifier.step(c, &mut p, &gr);
            for (j, &pj) in p.iter().take(d).enumerate() {
                m.weights[[c, j]] = pj;
            }
            m.bias[c] = p[d];
        }
        g.clear();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    fn tiny() -> (Model<f64>, PixelBatch) {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        use rand::Rng;
        let (n, d, c) = (7, 3, 5);
        let m = Model {
            dim: d,
            codes: (0..n * d).map(|_| rng.random_range(-1.0..1.0)).collect(),
            weights: Array2::from_shape_fn((c, d), |_| rng.random_range(-2.0..2.0)),
            bias: (0..c).map(|_| rng.random_range(-0.5..0.5)).collect(),
        };
        let mut b = PixelBatch::default();
        b.push(&[0, 1, 2], &[0.5, 0.3, 0.1], 1);
        b.push(&[2, 3], &[0.9, 0.05], 0);
        b.push(&[], &[], 2);
        b.push(&[4, 5, 6, 0], &[0.2, 0.2, 0.2, 0.2], 1);
        (m, b)
    }

    #[test]
    fn cross_entropy_matches_a_direct_formula() {
        let (m, b) = tiny();
        let mut g = Grads::new(&m);
        let got = cross_entropy(&m, &b, &Active::full(5), 1.0, &mut g);
        let group = [0u32, 1, 2, 1, 2];
        // Direct: per pixel, E = Σ w e, z = W E + b, CE = lse(z) − z_t.
        let mut want = 0.0;
        let mut want_mixed = 0.0;
        for p in 0..b.len() {
            let (ids, ws) = b.row(p);
            let mut e = [0.0; 3];
            for (&i, &w) in ids.iter().zip(ws) {
                for (j, ej) in e.iter_mut().enumerate() {
                    *ej += f64::from(w) * m.codes[i as usize * 3 + j];
                }
            }
            let z: Vec<f64> = (0..5)
                .map(|c| (0..3).map(|j| m.weights[[c, j]] * e[j]).sum::<f64>() + m.bias[c])
                .collect();
            let lz = z.iter().map(|x| x.exp()).sum::<f64>().ln();
            want += lz - z[b.targets[p] as usize];
            // Class term: groups {0}, {1, 3}, {2, 4}; −log of the target group's probability.
            let gt = group[b.targets[p] as usize];
            let pg: f64 = (0..5)
                .filter(|&c| group[c] == gt)
                .map(|c| (z[c] - lz).exp())
                .sum();
            want_mixed += 0.7 * (lz - z[b.targets[p] as usize]) - 0.3 * pg.ln();
        }
        assert!((got - want).abs() < 1e-12, "{got} vs {want}");
        let mixed = cross_entropy_mixed(&m, &b, &Active::full(5), &group, 0.3, 1.0, &mut g);
        assert!(
            (mixed - want_mixed).abs() < 1e-12,
            "{mixed} vs {want_mixed}"
        );
        assert!(
            mixed < got,
            "the group term forgives confusions inside a group"
        );
    }

    #[test]
    fn sampled_active_set_with_all_negatives_is_exact() {
        let (m, b) = tiny();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        let a = Active::sampled(5, vec![2, 0, 1, 1], 10, &mut rng);
        assert_eq!(a.members, [0, 1, 2]);
        assert_eq!(a.negatives, [3, 4]);
        assert_eq!(a.log_omega, 0.0);
        let (mut g1, mut g2) = (Grads::new(&m), Grads::new(&m));
        let l1 = cross_entropy(&m, &b, &Active::full(5), 1.0, &mut g1);
        let l2 = cross_entropy(&m, &b, &a, 1.0, &mut g2);
        assert!((l1 - l2).abs() < 1e-12);
        // Same gradient (the columns are a permutation of the classes).
        for (x, y) in g1.codes.iter().zip(&g2.codes) {
            assert!((x - y).abs() < 1e-12);
        }
        // One negative out of two: ω = 2.
        let a = Active::sampled(5, vec![0, 1, 2], 1, &mut rng);
        assert_eq!(a.negatives.len(), 1);
        assert!((a.log_omega - 2f64.ln()).abs() < 1e-15);
    }

    #[test]
    fn kl_of_identical_codes_is_zero_and_positive_otherwise() {
        let (mut m, _) = tiny();
        let c0: Vec<f64> = m.code(0).to_vec();
        m.codes[3..6].copy_from_slice(&c0);
        let mut g = Grads::new(&m);
        let (l, best) = knn_kl(&m, &[0], &[1], 1, &[Active::full(5)], 1.0, &mut g);
        assert!(l.abs() < 1e-15, "{l}");
        assert_eq!(best[0], best[1]);
        assert!(g.codes.iter().all(|x| x.abs() < 1e-12));
        let (l, _) = knn_kl(
            &m,
            &[0],
            &[2],
            1,
            &[Active::full(5)],
            1.0,
            &mut Grads::new(&m),
        );
        assert!(l > 0.0);
    }
}
