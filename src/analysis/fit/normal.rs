//! The fit's numerics: the normal equations JᵀJ, Jᵀr and ‖r‖² accumulated tile by tile from the
//! beads' windows of template samples (the separable sampler, the windows' own and pair sums,
//! the dot products), and the pixel-major reference they are tested against (see the parent
//! module's "Normal equations (speed)"). The AVX2 entry points are in `simd.rs`; the problem
//! (images, windows, model) in `problem.rs`.

use super::problem::*;
use super::simd as kernels;
use super::window::*;
use crate::optics::grid::GradStencil;
use nalgebra::{DMatrix, DVector};

impl FitData<'_> {
    /// Accumulate RSS, JᵀJ and Jᵀr at parameters p = [C, x, y]ᵢ.
    ///
    /// Tile by tile and block-sparse ([`FitData::tile_sums`], tiles of [`TILE_ROWS`] ×
    /// [`TILE_COLS`] pixels, in parallel). In each tile, the window of every bead that reaches it
    /// (the pixels within the template's extent, cut to the tile) is sampled into six contiguous
    /// planes — Sx, ∂Sx/∂u, ∂Sx/∂v, Sy, ∂Sy/∂u, ∂Sy/∂v, each zero where that channel's datum is
    /// invalid or the channel is not fitted — by a separable Keys cubic ([`TplPlanes`],
    /// [`kernels`]): per window row the four-tap v-stencil over the template columns the window
    /// reaches, then per pixel the four-tap u-stencil. The tile's model is the sum of its windows
    /// in bead order; its share of JᵀJ comes block by block: a bead's own 3 × 3 block and its Jᵀr,
    /// and a pair's off-diagonal block only where the two windows overlap (beads whose windows
    /// never overlap do not couple: their block is zero), all as dot products over contiguous
    /// rows with four accumulators. The tiles' parts are summed in tile order (the same result
    /// for any number of threads). The work is O(beads × window pixels + overlaps). The sums run
    /// in another order than the pixel-major reference, so the results agree with it to rounding
    /// (≲ 1e-13 relative, tested), not bit for bit.
    pub(super) fn accumulate(&self, p: &[f64]) -> (f64, DMatrix<f64>, DVector<f64>) {
        #[cfg(test)]
        if self.reference {
            return self.accumulate_reference(p, true);
        }
        use rayon::prelude::*;
        let nb = p.len() / 3;
        let np = p.len();
        let nx = self.nx();
        let shapes = self.windows(p);
        let ny = self.y.len();
        let outs: Vec<TileSums> = tiles(ny, nx)
            .par_iter()
            .map(|(tr, tc)| {
                let mut sc = self.scratch_take();
                let out = self.tile_sums(p, &shapes, tr.clone(), tc.clone(), &mut sc);
                self.scratch_give(sc);
                out
            })
            .collect();
        // Sum the tiles' parts in tile order (the same result for any number of threads).
        let mut rss = 0.0;
        let mut own = vec![([[0.0; 3]; 3], [0.0; 3]); nb];
        let mut pairs: std::collections::BTreeMap<(usize, usize), [[f64; 3]; 3]> =
            Default::default();
        for t in &outs {
            rss += t.rss;
            for &(i, a, g) in &t.own {
                let (oa, og) = &mut own[i];
                for x in 0..3 {
                    og[x] += g[x];
                    for y in 0..3 {
                        oa[x][y] += a[x][y];
                    }
                }
            }
            for &(i, j, b) in &t.pairs {
                let o = pairs.entry((i, j)).or_insert([[0.0; 3]; 3]);
                for x in 0..3 {
                    for y in 0..3 {
                        o[x][y] += b[x][y];
                    }
                }
            }
        }
        let inv_f = self.inv_f;
        // Scale of bead i's Jacobian columns relative to the planes: ∂r/∂C = S/f, ∂r/∂x = −C/f ∂S/∂u,
        // ∂r/∂y = −C/f ∂S/∂v.
        let scale = |i: usize| -> [f64; 3] {
            let w = p[3 * i] * inv_f;
            [inv_f, -w, -w]
        };
        let mut jtj = DMatrix::<f64>::zeros(np, np);
        let mut jtr = DVector::<f64>::zeros(np);
        for (i, (a, g)) in own.iter().enumerate() {
            let f = scale(i);
            for x in 0..3 {
                jtr[3 * i + x] = g[x] * f[x];
                for y in 0..3 {
                    jtj[(3 * i + x, 3 * i + y)] = a[x][y] * (f[x] * f[y]);
                }
            }
        }
        for (&(i, j), blk) in &pairs {
            let (fa, fb) = (scale(i), scale(j));
            for x in 0..3 {
                for y in 0..3 {
                    let v = blk[x][y] * (fa[x] * fb[y]);
                    jtj[(3 * i + x, 3 * j + y)] = v;
                    jtj[(3 * j + y, 3 * i + x)] = v;
                }
            }
        }
        (rss, jtj, jtr)
    }

    /// One tile's part of [`FitData::accumulate`]: the windows of the beads that reach the tile
    /// (rows `tr` × columns `tc` of the image) sampled over the tile only, the model and the
    /// residuals there, and the tile's share of the RSS, of each bead's own block and Jᵀr, and
    /// of each overlapping pair's block (unscaled). Everything a tile touches stays in the
    /// core's cache.
    pub(super) fn tile_sums(
        &self,
        p: &[f64],
        shapes: &[Shape],
        tr: std::ops::Range<usize>,
        tc: std::ops::Range<usize>,
        sc: &mut Scratch,
    ) -> TileSums {
        let nx = self.nx();
        let (th, tw) = (tr.len(), tc.len());
        let items = tile_items(shapes, &tr, &tc);
        let mut out = TileSums::default();
        if items.is_empty() {
            // No bead: the residual is minus the data.
            for &ch in self.chans {
                for r in tr.clone() {
                    let k0 = r * nx + tc.start;
                    for (d, mk) in self.ch_data[ch][k0..k0 + tw]
                        .iter()
                        .zip(&self.mask[ch][k0..k0 + tw])
                    {
                        if *mk != 0.0 {
                            out.rss += d * d;
                        }
                    }
                }
            }
            return out;
        }
        let (buf, res) = sc;
        let wins = self.sample_tile(p, &items, &tr, &tc, Some(&self.mask), buf);
        // Model (beads in index order at every pixel), then residuals: model − data where the
        // datum is valid and the channel fitted, 0 elsewhere.
        for r in res.iter_mut() {
            r.clear();
            r.resize(th * tw, 0.0);
        }
        self.add_model(p, &items, &wins, self.chans, tw, res);
        for &ch in self.chans {
            let mut acc = [0.0; 4];
            for r in 0..th {
                let k0 = (tr.start + r) * nx + tc.start;
                let e = &mut res[ch][r * tw..(r + 1) * tw];
                let (d, mk) = (&self.ch_data[ch][k0..k0 + tw], &self.mask[ch][k0..k0 + tw]);
                for (k, ((e, d), mk)) in e.iter_mut().zip(d).zip(mk).enumerate() {
                    let v = if *mk != 0.0 { *e - d } else { 0.0 };
                    *e = v;
                    acc[k & 3] += v * v;
                }
            }
            out.rss += (acc[0] + acc[1]) + (acc[2] + acc[3]);
        }
        for ((i, _, _), w) in items.iter().zip(&wins) {
            let (a, g) = w.own_sums(res, self.chans, tw);
            out.own.push((*i, a, g));
        }
        for (x, (i, _, _)) in items.iter().enumerate() {
            for (y, (j, _, _)) in items.iter().enumerate().skip(x + 1) {
                let (a, b) = (&wins[x], &wins[y]);
                if a.rows.start.max(b.rows.start) < a.rows.end.min(b.rows.end)
                    && a.cols.start.max(b.cols.start) < a.cols.end.min(b.cols.end)
                {
                    out.pairs
                        .push((*i, *j, Window::pair_sums(a, b, self.chans)));
                }
            }
        }
        out
    }

    /// The windows of `items` (see [`tile_items`]) sampled into `buf`, with rows and columns
    /// relative to the tile's first pixel.
    pub(super) fn sample_tile<'b>(
        &self,
        p: &[f64],
        items: &[TileItem],
        tr: &std::ops::Range<usize>,
        tc: &std::ops::Range<usize>,
        mask: Option<&[Vec<f64>; 2]>,
        buf: &'b mut Vec<f64>,
    ) -> Vec<Window<'b>> {
        let total: usize = items.iter().map(|(_, r, c)| r.len() * c.len()).sum();
        // Every element is written by `sample_window`.
        buf.resize(6 * total, 0.0);
        let mut wins: Vec<Window> = Vec::with_capacity(items.len());
        let mut rest = &mut buf[..6 * total];
        for (i, rows, cols) in items {
            let (s, b) = rest.split_at_mut(6 * rows.len() * cols.len());
            rest = b;
            let at = WindowAt {
                bx: p[3 * i + 1],
                by: p[3 * i + 2],
                rows: rows.clone(),
                cols: cols.clone(),
            };
            self.sample_window(at, mask, s);
            wins.push(Window {
                rows: rows.start - tr.start..rows.end - tr.start,
                cols: cols.start - tc.start..cols.end - tc.start,
                s,
            });
        }
        wins
    }

    /// Samples of the template around a bead over its window `at` (the bead at (bx, by) µm,
    /// pixel rows × cols) into `out`: six planes of rows.len() × cols.len() (see
    /// [`FitData::accumulate`]), zero where `mask` is 0 (the fit's mask: the channel's datum invalid or the channel not
    /// fitted; None: nowhere). Every element of `out` is written. Derivatives in
    /// instrument units per µm, as [`Grid2::eval_grad`](crate::optics::grid::Grid2::eval_grad).
    ///
    /// On x86-64 CPUs with AVX2 the same code runs compiled for AVX2 + FMA (runtime dispatch;
    /// the binary still runs on any x86-64 and other targets). No multiply–add is contracted
    /// into an FMA (Rust does not contract without `mul_add`), so both paths round alike.
    pub(super) fn sample_window(
        &self,
        at: WindowAt,
        mask: Option<&[Vec<f64>; 2]>,
        out: &mut [f64],
    ) {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
        {
            // SAFETY: the CPU supports the features the function is compiled for (checked just
            // above).
            unsafe { self.sample_window_avx2(at, mask, out) };
            return;
        }
        self.sample_window_impl::<false>(at, mask, out)
    }

    /// `SIMD`: use the AVX2 kernels (only from [`FitData::sample_window_avx2`]).
    #[inline(always)]
    pub(super) fn sample_window_impl<const SIMD: bool>(
        &self,
        at: WindowAt,
        mask: Option<&[Vec<f64>; 2]>,
        out: &mut [f64],
    ) {
        let WindowAt { bx, by, rows, cols } = at;
        let grid = &self.tpl.grid;
        let nc = cols.len();
        let npix = rows.len() * nc;
        if npix == 0 {
            // a bead whose window lies wholly outside the image (a fit can walk one there)
            return;
        }
        let nx = self.nx();
        let su: Option<Vec<GradStencil>> = match &self.planes {
            Some(_) => cols
                .clone()
                .map(|c| grid.grad_stencil_u(self.x[c] - bx))
                .collect(),
            None => None,
        };
        match (&self.planes, su) {
            (Some(tp), Some(su)) => {
                // Template columns the window reaches (stencil starts ≥ −1).
                let lo = su
                    .iter()
                    .filter(|s| s.inside)
                    .map(|s| s.first)
                    .min()
                    .unwrap_or(0);
                let hi = su
                    .iter()
                    .filter(|s| s.inside)
                    .map(|s| s.first + 4)
                    .max()
                    .unwrap_or(0);
                let width = (hi - lo).max(0) as usize;
                // Per window column: where its four taps start in the row buffer, and the Keys
                // weights and their derivatives; a column outside the template reads the first
                // taps with zero weights (its samples are zero, as `eval_grad`'s).
                let cols_st: Vec<(usize, [f64; 4], [f64; 4])> = su
                    .iter()
                    .map(|s| {
                        if s.inside {
                            ((s.first - lo) as usize, s.w, s.d)
                        } else {
                            (0, [0.0; 4], [0.0; 4])
                        }
                    })
                    .collect();
                // One window row's v-interpolated template columns, both channels and the
                // v-derivative together: node k = [Sx, Sy, ∂Sx/∂v·h, ∂Sy/∂v·h].
                let mut vrow = vec![[0.0f64; 4]; width];
                let ones = if mask.is_none() {
                    vec![1.0; nc]
                } else {
                    Vec::new()
                };
                let inv_h = 1.0 / grid.h;
                for (rr, r) in rows.enumerate() {
                    let sv = grid.grad_stencil_v(self.y[r] - by);
                    let sv = match sv {
                        Some(s) if s.inside && width > 0 => s,
                        _ => {
                            for pl in out.chunks_exact_mut(npix) {
                                pl[rr * nc..(rr + 1) * nc].fill(0.0);
                            }
                            continue;
                        }
                    };
                    let taps = [0, 1, 2, 3].map(|b| tp.row(sv.first + b as isize, lo, width));
                    if taps.iter().any(|t| t.len() != width) {
                        // Outside the padded grid (cannot happen for `grad_stencil_*`'s stencils).
                        for pl in out.chunks_exact_mut(npix) {
                            pl[rr * nc..(rr + 1) * nc].fill(0.0);
                        }
                        continue;
                    }
                    #[cfg(target_arch = "x86_64")]
                    if SIMD {
                        // SAFETY: SIMD is true only in `sample_window_avx2`, called after the
                        // CPU was found to support AVX2 and FMA.
                        unsafe { kernels::v_pass_avx2(&mut vrow, taps, &sv.w, &sv.d) };
                    } else {
                        kernels::v_pass(&mut vrow, taps, &sv.w, &sv.d);
                    }
                    #[cfg(not(target_arch = "x86_64"))]
                    kernels::v_pass(&mut vrow, taps, &sv.w, &sv.d);
                    let at = rr * nc;
                    let k0 = r * nx + cols.start;
                    let (m0, m1) = match mask {
                        Some(m) => (&m[0][k0..k0 + nc], &m[1][k0..k0 + nc]),
                        None => (&ones[..], &ones[..]),
                    };
                    let (o0, rest) = out.split_at_mut(npix);
                    let (o1, rest) = rest.split_at_mut(npix);
                    let (o2, rest) = rest.split_at_mut(npix);
                    let (o3, rest) = rest.split_at_mut(npix);
                    let (o4, o5) = rest.split_at_mut(npix);
                    let [o0, o1, o2, o3, o4, o5] =
                        [o0, o1, o2, o3, o4, o5].map(|pl| &mut pl[at..at + nc]);
                    let o = [o0, o1, o2, o3, o4, o5];
                    #[cfg(target_arch = "x86_64")]
                    if SIMD {
                        // SAFETY: as for the v pass.
                        unsafe { kernels::u_pass_avx2(o, &vrow, &cols_st, [m0, m1], inv_h) };
                    } else {
                        kernels::u_pass(o, &vrow, &cols_st, [m0, m1], inv_h);
                    }
                    #[cfg(not(target_arch = "x86_64"))]
                    kernels::u_pass(o, &vrow, &cols_st, [m0, m1], inv_h);
                }
            }
            _ => {
                for (rr, r) in rows.enumerate() {
                    let v = self.y[r] - by;
                    for (cc, c) in cols.clone().enumerate() {
                        let k = r * nx + c;
                        let e = grid.eval_grad(self.x[c] - bx, v);
                        let at = rr * nc + cc;
                        for ch in 0..2 {
                            let on = mask.is_none_or(|m| m[ch][k] != 0.0);
                            let z = |v: f64| if on { v } else { 0.0 };
                            out[3 * ch * npix + at] = z(e.v[ch]);
                            out[(3 * ch + 1) * npix + at] = z(e.du[ch]);
                            out[(3 * ch + 2) * npix + at] = z(e.dv[ch]);
                        }
                    }
                }
            }
        }
    }

    /// The pixel-major accumulation used before the speed work (one `eval_grad` per bead and pixel,
    /// JᵀJ filled pixel by pixel), kept as the reference that [`FitData::accumulate`] must
    /// reproduce bit for bit.
    #[cfg(test)]
    pub(super) fn accumulate_reference(
        &self,
        p: &[f64],
        want_normal: bool,
    ) -> (f64, DMatrix<f64>, DVector<f64>) {
        let nb = p.len() / 3;
        let np = p.len();
        let mut jtj = DMatrix::<f64>::zeros(
            if want_normal { np } else { 0 },
            if want_normal { np } else { 0 },
        );
        let mut jtr = DVector::<f64>::zeros(if want_normal { np } else { 0 });
        let ((u0, u1), (v0, v1)) = self.tpl.extent();
        let cr: Vec<std::ops::Range<usize>> = (0..nb)
            .map(|i| self.ax.range(p[3 * i + 1] + u0, p[3 * i + 1] + u1))
            .collect();
        let rr: Vec<std::ops::Range<usize>> = (0..nb)
            .map(|i| self.ay.range(p[3 * i + 2] + v0, p[3 * i + 2] + v1))
            .collect();
        let nx = self.nx();
        let mut rss = 0.0;
        let mut act: Vec<(usize, f64, crate::optics::grid::Sample)> = Vec::with_capacity(nb);
        let mut g = vec![0.0f64; np];
        let mut gi: Vec<usize> = Vec::with_capacity(np);
        let mut row_beads: Vec<usize> = Vec::with_capacity(nb);
        // Local 3k×3k accumulation: for each pixel the active parameter list is short.
        for r in 0..self.y.len() {
            row_beads.clear();
            row_beads.extend((0..nb).filter(|&i| rr[i].contains(&r)));
            let yv = self.y[r];
            for c in 0..nx {
                let k = r * nx + c;
                let valid: [bool; 2] = [
                    self.ch_data[0][k].is_finite(),
                    self.ch_data[1][k].is_finite(),
                ];
                if !self.chans.iter().any(|&ch| valid[ch]) {
                    continue;
                }
                act.clear();
                for &i in &row_beads {
                    if cr[i].contains(&c) {
                        let s = if want_normal {
                            self.tpl
                                .eval_grad(self.x[c] - p[3 * i + 1], yv - p[3 * i + 2])
                        } else {
                            crate::optics::grid::Sample {
                                v: self.tpl.eval(self.x[c] - p[3 * i + 1], yv - p[3 * i + 2]),
                                ..Default::default()
                            }
                        };
                        // Weights are in reference-bead units, the data in instrument units.
                        act.push((i, p[3 * i] * self.inv_f, s));
                    }
                }
                for &ch in self.chans {
                    if !valid[ch] {
                        continue;
                    }
                    let mut model = 0.0;
                    for &(_, w, s) in &act {
                        model += w * s.v[ch];
                    }
                    let res = model - self.ch_data[ch][k];
                    rss += res * res;
                    if want_normal && !act.is_empty() {
                        gi.clear();
                        for &(i, w, s) in &act {
                            g[3 * i] = s.v[ch] * self.inv_f;
                            g[3 * i + 1] = -w * s.du[ch];
                            g[3 * i + 2] = -w * s.dv[ch];
                            gi.extend_from_slice(&[3 * i, 3 * i + 1, 3 * i + 2]);
                        }
                        for (a, &ia) in gi.iter().enumerate() {
                            let ga = g[ia];
                            jtr[ia] += ga * res;
                            for &ib in &gi[a..] {
                                jtj[(ia, ib)] += ga * g[ib];
                            }
                        }
                    }
                }
            }
        }
        if want_normal {
            // Symmetrise (only pairs (ia ≤ ib in the per-pixel order) were filled).
            for a in 0..np {
                for b in a + 1..np {
                    let s = jtj[(a, b)] + jtj[(b, a)];
                    jtj[(a, b)] = s;
                    jtj[(b, a)] = s;
                }
            }
        }
        (rss, jtj, jtr)
    }
}

/// A tile's part of the sums (see [`FitData::tile_sums`]).
#[derive(Default)]
pub(super) struct TileSums {
    pub(super) rss: f64,
    /// (bead, Σ Jₓ·J_y, Σ Jₓ·e), unscaled.
    pub(super) own: Vec<(usize, [[f64; 3]; 3], [f64; 3])>,
    /// (bead i, bead j > i, Σ Jᵢₓ·Jⱼ_y), unscaled.
    pub(super) pairs: Vec<(usize, usize, [[f64; 3]; 3])>,
}
