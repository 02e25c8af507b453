//! `Grid2`: three signal channels (Sx, Sy, Sz) sampled on a regular 2-D grid of displacements,
//! with linear or cubic-convolution interpolation and analytic derivatives.
//!
//! This is the storage behind every template: the physics model's precomputed single-scatterer
//! response (`optics::template`) and templates measured from reference-bead scans
//! (`analysis`). Outside the grid the response is taken as zero: templates are built wide enough
//! that the response there is negligible (the builder states the truncation level).
//!
//! Interpolation error (tested in `tests/optics.rs`): linear is O(h²), cubic convolution
//! (Keys 1981, a = −1/2) is O(h³) for smooth data.

use serde::{Deserialize, Serialize};

/// Interpolation order, a documented accuracy knob.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Interp {
    Linear,
    #[default]
    Cubic,
}

impl Interp {
    pub fn parse(s: &str) -> Option<Self> {
        match s {
            "linear" => Some(Self::Linear),
            "cubic" => Some(Self::Cubic),
            _ => None,
        }
    }
}

/// Values and first derivatives of the first `N` channels (Sx, Sy, Sz) at one point.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Samples<const N: usize> {
    /// (Sx, Sy, Sz), the first `N` of them.
    pub v: [f64; N],
    /// ∂/∂u of the values along the grid's first (horizontal) coordinate.
    pub du: [f64; N],
    /// ∂/∂v along the second (vertical) coordinate.
    pub dv: [f64; N],
}

impl<const N: usize> Default for Samples<N> {
    fn default() -> Self {
        Self {
            v: [0.0; N],
            du: [0.0; N],
            dv: [0.0; N],
        }
    }
}

/// Values and first derivatives of the three channels at one point.
pub type Sample = Samples<3>;

/// Values and first derivatives of Sx and Sy (channels 0 and 1 of [`Sample`]).
pub type Sample2 = Samples<2>;

/// Precomputed stencil of one axis for [`Grid2::eval_grad2_stencil`] (see
/// [`Grid2::grad_stencil_u`]).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct GradStencil {
    /// The coordinate lies inside the node extent (else the sample is zero).
    pub inside: bool,
    /// Index of the stencil's first node (may be −1 at the border: nodes outside count as 0).
    pub first: isize,
    /// Keys weights and their derivatives with respect to the fraction (not yet divided by h).
    pub w: [f64; 4],
    pub d: [f64; 4],
    /// All four nodes lie inside the grid (no bounds checks needed).
    pub full: bool,
}

/// Regular grid: node (i, j) sits at (u0 + i·h, v0 + j·h); values stored interleaved
/// `[sx, sy, sz]` per node, row-major in j (so rows = v).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Grid2 {
    pub u0: f64,
    pub v0: f64,
    /// Node spacing (µm), the same along both coordinates.
    pub h: f64,
    pub nu: usize,
    pub nv: usize,
    pub data: Vec<[f64; 3]>,
    pub interp: Interp,
}

impl Grid2 {
    /// A square grid of n × n nodes from (u0, u0), spacing `h` (µm), with its node values
    /// (`data`, row-major in v, n² entries).
    pub fn square(u0: f64, h: f64, n: usize, data: Vec<[f64; 3]>, interp: Interp) -> Self {
        debug_assert_eq!(data.len(), n * n);
        Self {
            u0,
            v0: u0,
            h,
            nu: n,
            nv: n,
            data,
            interp,
        }
    }

    /// Build a grid by evaluating `f(u, v)` at every node.
    pub fn from_fn(
        u0: f64,
        v0: f64,
        h: f64,
        nu: usize,
        nv: usize,
        interp: Interp,
        mut f: impl FnMut(f64, f64) -> [f64; 3],
    ) -> Self {
        let mut data = Vec::with_capacity(nu * nv);
        for j in 0..nv {
            let v = v0 + j as f64 * h;
            for i in 0..nu {
                data.push(f(u0 + i as f64 * h, v));
            }
        }
        Self {
            u0,
            v0,
            h,
            nu,
            nv,
            data,
            interp,
        }
    }

    /// Node value at integer indices (zero outside).
    #[inline]
    fn node(&self, i: isize, j: isize) -> [f64; 3] {
        if i < 0 || j < 0 || i as usize >= self.nu || j as usize >= self.nv {
            [0.0; 3]
        } else {
            self.data[j as usize * self.nu + i as usize]
        }
    }

    /// Extent covered by the nodes: ((u_min, u_max), (v_min, v_max)).
    pub fn extent(&self) -> ((f64, f64), (f64, f64)) {
        (
            (self.u0, self.u0 + (self.nu.max(1) - 1) as f64 * self.h),
            (self.v0, self.v0 + (self.nv.max(1) - 1) as f64 * self.h),
        )
    }

    /// True when (u, v) lies inside the node extent.
    #[inline]
    pub fn contains(&self, u: f64, v: f64) -> bool {
        let ((a, b), (c, d)) = self.extent();
        u >= a && u <= b && v >= c && v <= d
    }

    /// Interpolated (Sx, Sy, Sz) at (u, v); zero outside the grid or for non-finite input.
    #[inline]
    pub fn eval(&self, u: f64, v: f64) -> [f64; 3] {
        if self.interp == Interp::Cubic && self.nu >= 4 && self.nv >= 4 {
            // hot path of every render: stencil fully inside → no bounds checks per node
            let fu = (u - self.u0) / self.h;
            let fv = (v - self.v0) / self.h;
            if fu >= 1.0 && fv >= 1.0 && fu < (self.nu - 2) as f64 && fv < (self.nv - 2) as f64 {
                let (iu, iv) = (fu as usize, fv as usize);
                let (wu, _) = keys(fu - iu as f64);
                let (wv, _) = keys(fv - iv as f64);
                return self.eval_stencil((iu - 1, &wu), (iv - 1, &wv));
            }
        }
        self.sample(u, v, false).v
    }

    /// The fast path's stencil along u: when the cubic stencil at `u` lies fully inside the
    /// grid along u, the first node index (iu − 1) and the four Keys weights, computed exactly as
    /// [`Grid2::eval`] computes them (so a caller can precompute them once per pixel column and
    /// get bit-identical values from [`Grid2::eval_stencil`]). `None` for linear grids, grids
    /// under 4 × 4 nodes, or a stencil reaching outside (then call [`Grid2::eval`]).
    #[inline]
    pub fn stencil_u(&self, u: f64) -> Option<(usize, [f64; 4])> {
        self.stencil(u, self.u0, self.nu)
    }

    /// As [`Grid2::stencil_u`], along v.
    #[inline]
    pub fn stencil_v(&self, v: f64) -> Option<(usize, [f64; 4])> {
        self.stencil(v, self.v0, self.nv)
    }

    #[inline]
    fn stencil(&self, u: f64, u0: f64, n: usize) -> Option<(usize, [f64; 4])> {
        if self.interp != Interp::Cubic || self.nu < 4 || self.nv < 4 {
            return None;
        }
        let fu = (u - u0) / self.h;
        if fu >= 1.0 && fu < (n - 2) as f64 {
            let iu = fu as usize;
            Some((iu - 1, keys(fu - iu as f64).0))
        } else {
            None
        }
    }

    /// Cubic interpolation from precomputed stencils ([`Grid2::stencil_u`],
    /// [`Grid2::stencil_v`]): [`Grid2::eval`]'s fast path itself, so the result is
    /// bit-identical to `eval(u, v)`.
    #[inline]
    pub fn eval_stencil(&self, su: (usize, &[f64; 4]), sv: (usize, &[f64; 4])) -> [f64; 3] {
        let (iu, wu) = su;
        let (iv, wv) = sv;
        let mut out = [0.0; 3];
        for (b, &wvb) in wv.iter().enumerate() {
            let base = (iv + b) * self.nu + iu;
            let row = &self.data[base..base + 4];
            let mut acc = [0.0; 3];
            for (n, &wua) in row.iter().zip(wu) {
                acc[0] += wua * n[0];
                acc[1] += wua * n[1];
                acc[2] += wua * n[2];
            }
            out[0] += wvb * acc[0];
            out[1] += wvb * acc[1];
            out[2] += wvb * acc[2];
        }
        out
    }

    /// Location (u, v) and value of the maximum of `f` over the grid's extent: the best inner
    /// node, then three rounds of a 9×9 local search whose step shrinks 4× each round (h/4,
    /// h/16, h/64: the last resolves the peak to h/128). Used for a template's maximum
    /// sensitivity and its detection response's peak.
    pub fn max_of(&self, f: impl Fn(f64, f64) -> f64) -> (f64, f64, f64) {
        let mut best = (0.0, 0.0, f64::NEG_INFINITY);
        for j in 1..self.nv.saturating_sub(1) {
            for i in 1..self.nu.saturating_sub(1) {
                let (u, v) = (self.u0 + i as f64 * self.h, self.v0 + j as f64 * self.h);
                let d = f(u, v);
                if d > best.2 {
                    best = (u, v, d);
                }
            }
        }
        let mut step = self.h / 4.0;
        for _ in 0..3 {
            let (cu, cv) = (best.0, best.1);
            for b in -4..=4 {
                for a in -4..=4 {
                    let (u, v) = (cu + a as f64 * step, cv + b as f64 * step);
                    let d = f(u, v);
                    if d > best.2 {
                        best = (u, v, d);
                    }
                }
            }
            step /= 4.0;
        }
        best
    }

    /// Values and derivatives at (u, v).
    #[inline]
    pub fn eval_grad(&self, u: f64, v: f64) -> Sample {
        self.sample(u, v, true)
    }

    fn sample(&self, u: f64, v: f64, grad: bool) -> Sample {
        let mut out = Sample::default();
        if !self.contains(u, v) || self.nu < 2 || self.nv < 2 {
            return out;
        }
        let fu = (u - self.u0) / self.h;
        let fv = (v - self.v0) / self.h;
        let iu = (fu.floor() as isize).min(self.nu as isize - 2);
        let iv = (fv.floor() as isize).min(self.nv as isize - 2);
        let tu = fu - iu as f64;
        let tv = fv - iv as f64;
        let inv_h = 1.0 / self.h;
        match self.interp {
            Interp::Linear => {
                let wu = [1.0 - tu, tu];
                let wv = [1.0 - tv, tv];
                let du = [-inv_h, inv_h];
                let dv = [-inv_h, inv_h];
                for (b, (&wvb, &dvb)) in wv.iter().zip(&dv).enumerate() {
                    for (a, (&wua, &dua)) in wu.iter().zip(&du).enumerate() {
                        let n = self.node(iu + a as isize, iv + b as isize);
                        for c in 0..3 {
                            out.v[c] += wua * wvb * n[c];
                            if grad {
                                out.du[c] += dua * wvb * n[c];
                                out.dv[c] += wua * dvb * n[c];
                            }
                        }
                    }
                }
            }
            Interp::Cubic => {
                let (wu, du) = keys(tu);
                let (wv, dv) = keys(tv);
                for b in 0..4 {
                    let jj = iv - 1 + b as isize;
                    // row partial sums
                    let mut row = [0.0; 3];
                    let mut row_du = [0.0; 3];
                    for a in 0..4 {
                        let n = self.node(iu - 1 + a as isize, jj);
                        for c in 0..3 {
                            row[c] += wu[a] * n[c];
                            if grad {
                                row_du[c] += du[a] * n[c];
                            }
                        }
                    }
                    for c in 0..3 {
                        out.v[c] += wv[b] * row[c];
                        if grad {
                            out.du[c] += wv[b] * row_du[c] * inv_h;
                            out.dv[c] += dv[b] * row[c] * inv_h;
                        }
                    }
                }
            }
        }
        out
    }

    /// One axis of [`Grid2::eval_grad`]'s cubic stencil at coordinate `u` (along u), computed
    /// exactly as `eval_grad` computes it, so that a caller sampling many pixels of one row or
    /// column can compute it once and get bit-identical values from
    /// [`Grid2::eval_grad2_stencil`]. `None` for linear grids and grids under 2 × 2 nodes (call
    /// `eval_grad` there).
    #[inline]
    pub fn grad_stencil_u(&self, u: f64) -> Option<GradStencil> {
        let ((a, b), _) = self.extent();
        self.grad_stencil(u, self.u0, self.nu, a, b)
    }

    /// As [`Grid2::grad_stencil_u`], along v.
    #[inline]
    pub fn grad_stencil_v(&self, v: f64) -> Option<GradStencil> {
        let (_, (a, b)) = self.extent();
        self.grad_stencil(v, self.v0, self.nv, a, b)
    }

    #[inline]
    fn grad_stencil(&self, u: f64, u0: f64, n: usize, lo: f64, hi: f64) -> Option<GradStencil> {
        if self.interp != Interp::Cubic || self.nu < 2 || self.nv < 2 {
            return None;
        }
        let inside = u >= lo && u <= hi;
        let fu = (u - u0) / self.h;
        let i = if inside {
            (fu.floor() as isize).min(n as isize - 2)
        } else {
            0
        };
        let (w, d) = if inside {
            keys(fu - i as f64)
        } else {
            ([0.0; 4], [0.0; 4])
        };
        Some(GradStencil {
            inside,
            first: i - 1,
            w,
            d,
            full: inside && i >= 1 && i + 2 < n as isize,
        })
    }

    /// Sx, Sy and their ∂/∂u, ∂/∂v (channels 0 and 1 of [`Grid2::eval_grad`]) from precomputed
    /// stencils: the same arithmetic in the same order, so the values are bit-identical to
    /// `eval_grad(u, v)`'s (tested). Zero outside the grid, as there.
    #[inline]
    pub fn eval_grad2_stencil(&self, su: &GradStencil, sv: &GradStencil) -> Sample2 {
        let mut out = Sample2::default();
        if !(su.inside && sv.inside) {
            return out;
        }
        let inv_h = 1.0 / self.h;
        let node = |i: isize, j: isize| -> [f64; 3] {
            if su.full && sv.full {
                self.data[j as usize * self.nu + i as usize]
            } else {
                self.node(i, j)
            }
        };
        for b in 0..4 {
            let jj = sv.first + b as isize;
            let mut row = [0.0; 2];
            let mut row_du = [0.0; 2];
            for a in 0..4 {
                let n = node(su.first + a as isize, jj);
                for c in 0..2 {
                    row[c] += su.w[a] * n[c];
                    row_du[c] += su.d[a] * n[c];
                }
            }
            for c in 0..2 {
                out.v[c] += sv.w[b] * row[c];
                out.du[c] += sv.w[b] * row_du[c] * inv_h;
                out.dv[c] += sv.d[b] * row[c] * inv_h;
            }
        }
        out
    }

    /// Memory held by the node values, bytes.
    pub fn bytes(&self) -> usize {
        self.data.len() * std::mem::size_of::<[f64; 3]>()
    }
}

/// Keys (1981) cubic-convolution weights (a = −1/2) for nodes −1, 0, 1, 2 at fraction t.
#[inline]
pub(crate) fn keys_weights(t: f64) -> [f64; 4] {
    let t2 = t * t;
    let t3 = t2 * t;
    [
        0.5 * (-t3 + 2.0 * t2 - t),
        0.5 * (3.0 * t3 - 5.0 * t2 + 2.0),
        0.5 * (-3.0 * t3 + 4.0 * t2 + t),
        0.5 * (t3 - t2),
    ]
}

/// [`keys_weights`] and their derivatives with respect to t.
#[inline]
fn keys(t: f64) -> ([f64; 4], [f64; 4]) {
    let t2 = t * t;
    let w = keys_weights(t);
    let d = [
        0.5 * (-3.0 * t2 + 4.0 * t - 1.0),
        0.5 * (9.0 * t2 - 10.0 * t),
        0.5 * (-9.0 * t2 + 8.0 * t + 1.0),
        0.5 * (3.0 * t2 - 2.0 * t),
    ];
    (w, d)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn smooth(u: f64, v: f64) -> [f64; 3] {
        let g = (-(u * u + v * v) / 0.16).exp();
        [u * g, v * g, g]
    }

    #[test]
    fn reproduces_nodes_exactly_and_zero_outside() {
        let g = Grid2::from_fn(-1.0, -1.0, 0.05, 41, 41, Interp::Cubic, smooth);
        let (u, v) = (-1.0 + 13.0 * 0.05, -1.0 + 27.0 * 0.05);
        let s = g.eval(u, v);
        let e = smooth(u, v);
        for c in 0..3 {
            assert!((s[c] - e[c]).abs() < 1e-15);
        }
        assert_eq!(g.eval(1.2, 0.0), [0.0; 3]);
        assert_eq!(g.eval(f64::NAN, 0.0), [0.0; 3]);
    }

    #[test]
    fn cubic_error_scales_as_h3_and_beats_linear() {
        let err = |h: f64, interp| {
            let n = (2.0 / h).round() as usize + 1;
            let g = Grid2::from_fn(-1.0, -1.0, h, n, n, interp, smooth);
            let mut m: f64 = 0.0;
            for k in 0..200 {
                let u = -0.7 + 1.4 * (k as f64 * 0.6180339887).fract();
                let v = -0.7 + 1.4 * (k as f64 * 0.4142135623).fract();
                m = m.max((g.eval(u, v)[0] - smooth(u, v)[0]).abs());
            }
            m
        };
        let (c1, c2) = (err(0.04, Interp::Cubic), err(0.02, Interp::Cubic));
        let (l1, l2) = (err(0.04, Interp::Linear), err(0.02, Interp::Linear));
        assert!(c1 / c2 > 6.0, "cubic order: {c1} / {c2}");
        assert!(l1 / l2 > 3.5 && l1 / l2 < 4.5, "linear order: {l1} / {l2}");
        assert!(c2 < l2 / 5.0);
    }

    #[test]
    fn fast_path_equals_general_path() {
        let g = Grid2::from_fn(-1.0, -1.0, 0.05, 41, 41, Interp::Cubic, smooth);
        for k in 0..500 {
            let u = -1.1 + 2.2 * (k as f64 * 0.618_033_988_7).fract();
            let v = -1.1 + 2.2 * (k as f64 * 0.414_213_562_3).fract();
            let (a, b) = (g.eval(u, v), g.sample(u, v, false).v);
            for c in 0..3 {
                assert!((a[c] - b[c]).abs() < 1e-15, "({u}, {v})");
            }
        }
    }

    /// Precomputed stencils give exactly `eval`'s values, and say `None` where `eval` leaves
    /// its fast path.
    #[test]
    fn grad_stencils_are_bit_identical_to_eval_grad() {
        let g = Grid2::from_fn(-0.5, -0.4, 0.02, 51, 41, Interp::Cubic, smooth);
        let mut n_inside = 0;
        // Inside, at the borders (stencils reaching outside), exactly on nodes and the extent's
        // ends, and outside.
        for k in 0..=140 {
            for l in 0..=120 {
                let u = -0.54 + k as f64 * 0.0077;
                let v = -0.44 + l as f64 * 0.0071;
                for (u, v) in [(u, v), (0.5, v), (u, 0.4), (-0.5, -0.4), (0.5 - 1e-15, v)] {
                    let e = g.eval_grad(u, v);
                    let s = g.eval_grad2_stencil(
                        &g.grad_stencil_u(u).unwrap(),
                        &g.grad_stencil_v(v).unwrap(),
                    );
                    for c in 0..2 {
                        assert_eq!(e.v[c].to_bits(), s.v[c].to_bits(), "v at ({u}, {v})");
                        assert_eq!(e.du[c].to_bits(), s.du[c].to_bits(), "du at ({u}, {v})");
                        assert_eq!(e.dv[c].to_bits(), s.dv[c].to_bits(), "dv at ({u}, {v})");
                    }
                    n_inside += usize::from(e.v[0] != 0.0);
                }
            }
        }
        assert!(n_inside > 10_000);
        let lin = Grid2::from_fn(-0.5, -0.4, 0.02, 51, 41, Interp::Linear, smooth);
        assert!(lin.grad_stencil_u(0.0).is_none());
    }

    #[test]
    fn stencils_are_bit_identical_to_eval() {
        let g = Grid2::from_fn(-1.0, -1.0, 0.05, 41, 41, Interp::Cubic, smooth);
        let mut fast = 0;
        for k in 0..500 {
            let u = -1.1 + 2.2 * (k as f64 * 0.618_033_988_7).fract();
            let v = -1.1 + 2.2 * (k as f64 * 0.414_213_562_3).fract();
            if let (Some((iu, wu)), Some((iv, wv))) = (g.stencil_u(u), g.stencil_v(v)) {
                assert_eq!(
                    g.eval_stencil((iu, &wu), (iv, &wv)),
                    g.eval(u, v),
                    "({u}, {v})"
                );
                fast += 1;
            }
        }
        assert!(fast > 300, "{fast}");
        assert!(g.stencil_u(-0.96).is_none() && g.stencil_u(0.96).is_none());
        let lin = Grid2::from_fn(-1.0, -1.0, 0.05, 41, 41, Interp::Linear, smooth);
        assert!(lin.stencil_u(0.0).is_none());
    }

    #[test]
    fn derivative_matches_finite_difference() {
        let g = Grid2::from_fn(-1.0, -1.0, 0.02, 101, 101, Interp::Cubic, smooth);
        let (u, v) = (0.123, -0.071);
        let s = g.eval_grad(u, v);
        let e = 1e-5;
        for c in 0..3 {
            let fd_u = (g.eval(u + e, v)[c] - g.eval(u - e, v)[c]) / (2.0 * e);
            let fd_v = (g.eval(u, v + e)[c] - g.eval(u, v - e)[c]) / (2.0 * e);
            assert!((s.du[c] - fd_u).abs() < 1e-6, "du c={c}");
            assert!((s.dv[c] - fd_v).abs() < 1e-6, "dv c={c}");
        }
        // Close to the analytic slope of u·exp(-(u²+v²)/0.16) at the origin (= 1). At a node the
        // cubic-convolution derivative is the central difference, error h²/6·f''' = 0.0025 here.
        let slope = g.eval_grad(0.0, 0.0).du[0];
        assert!(
            (slope - (1.0 - 0.02f64.powi(2) / 6.0 * 37.5)).abs() < 1e-4,
            "slope {slope}"
        );
    }
}
