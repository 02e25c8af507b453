//! The fit's tiled problem: the images prepared for fitting, the beads' windows and template
//! samples, and the accumulation of JᵀJ, Jᵀr and ‖r‖² tile by tile (see the parent module's
//! "Normal equations (speed)").

use super::super::template::Template;
use super::super::{check_axis, AnalysisError, AxisMap, Result};
use super::lm::{levenberg_marquardt, scaled_condition, RawFit, Tolerances};
use super::simd as kernels;
use super::types::*;
use crate::data::Image;
use crate::optics::grid::GradStencil;
use nalgebra::{DMatrix, DVector};
use ndarray::Array2;

/// The images prepared for fitting.
pub(super) struct FitData<'a> {
    pub(super) tpl: &'a Template,
    pub(super) x: Vec<f64>,
    pub(super) y: Vec<f64>,
    pub(super) ax: AxisMap,
    pub(super) ay: AxisMap,
    /// Row-major (rows, cols) data of the two channels; NaN = invalid.
    pub(super) ch_data: [Vec<f64>; 2],
    pub(super) chans: &'static [usize],
    pub(super) m: usize,
    pub(super) area: f64,
    pub(super) w0: f64,
    pub(super) min_sep: f64,
    /// 1/norm_factor: instrument units per reference-bead unit.
    pub(super) inv_f: f64,
    /// Tile buffers reused from one evaluation to the next (one per tile in flight): no
    /// page-faulting allocation per evaluation. Taken from [`SCRATCH_POOL`] and given back on
    /// drop, so that the next fit does not allocate them again either.
    pub(super) scratch: std::sync::Mutex<Vec<Scratch>>,
    /// 1 where the channel is fitted and its datum valid, else 0 (row-major, per channel).
    pub(super) mask: [Vec<f64>; 2],
    /// The template's node values for the separable stencil (None for a linear or degenerate
    /// grid: those are sampled with `eval_grad`).
    pub(super) planes: Option<TplPlanes>,
    /// Tests only: accumulate with the pixel-major reference.
    #[cfg(test)]
    pub(super) reference: bool,
}

/// A tile's reused buffers: the windows' samples and the two residual images of the tile.
pub(super) type Scratch = (Vec<f64>, [Vec<f64>; 2]);

/// The tiles of [`FitData::accumulate`]: rows × columns of pixels. A tile's windows (six planes
/// of ≲ 32 × 32 samples for each bead that reaches it) stay in a core's L2 cache.
pub(super) const TILE_ROWS: usize = 32;
pub(super) const TILE_COLS: usize = 128;

/// A bead that reaches a tile: its index and its window's rows and columns cut to the tile.
pub(super) type TileItem = (usize, std::ops::Range<usize>, std::ops::Range<usize>);

/// Pixel ranges of a window.
pub(super) type Shape = (std::ops::Range<usize>, std::ops::Range<usize>);

/// The tiles (rows × columns) covering an image of ny × nx pixels, row-major.
pub(super) fn tiles(ny: usize, nx: usize) -> Vec<Shape> {
    (0..ny)
        .step_by(TILE_ROWS)
        .flat_map(|r0| {
            (0..nx)
                .step_by(TILE_COLS)
                .map(move |c0| (r0..(r0 + TILE_ROWS).min(ny), c0..(c0 + TILE_COLS).min(nx)))
        })
        .collect()
}

/// The beads whose windows (`shapes`) reach the tile `tr` × `tc`, in index order, with their
/// windows cut to the tile.
pub(super) fn tile_items(
    shapes: &[Shape],
    tr: &std::ops::Range<usize>,
    tc: &std::ops::Range<usize>,
) -> Vec<TileItem> {
    let cut = |a: &std::ops::Range<usize>, b: &std::ops::Range<usize>| {
        a.start.max(b.start)..a.end.min(b.end).max(a.start.max(b.start))
    };
    shapes
        .iter()
        .enumerate()
        .filter_map(|(i, (rows, cols))| {
            let (r, c) = (cut(rows, tr), cut(cols, tc));
            (!r.is_empty() && !c.is_empty()).then_some((i, r, c))
        })
        .collect()
}

/// A tile's part of the sums (see [`FitData::tile_sums`]).
#[derive(Default)]
pub(super) struct TileSums {
    rss: f64,
    /// (bead, Σ Jₓ·J_y, Σ Jₓ·e), unscaled.
    own: Vec<(usize, [[f64; 3]; 3], [f64; 3])>,
    /// (bead i, bead j > i, Σ Jᵢₓ·Jⱼ_y), unscaled.
    pairs: Vec<(usize, usize, [[f64; 3]; 3])>,
}

/// The tile buffers of the last fit, for the next one (allocating and zeroing a 40-bead fit's
/// buffers every fit was ~10 % of it). Kept only while they hold at most [`SCRATCH_KEEP`]
/// values.
pub(super) static SCRATCH_POOL: std::sync::Mutex<Vec<Scratch>> = std::sync::Mutex::new(Vec::new());
pub(super) const SCRATCH_KEEP: usize = 1 << 24;

impl Drop for FitData<'_> {
    fn drop(&mut self) {
        let s = std::mem::take(
            self.scratch
                .get_mut()
                .unwrap_or_else(std::sync::PoisonError::into_inner),
        );
        let held: usize = s
            .iter()
            .map(|(b, r)| b.capacity() + r[0].capacity() + r[1].capacity())
            .sum();
        if held <= SCRATCH_KEEP {
            *SCRATCH_POOL
                .lock()
                .unwrap_or_else(std::sync::PoisonError::into_inner) = s;
        }
    }
}

impl<'a> FitData<'a> {
    pub(super) fn new(
        sx: &Image,
        sy: &Image,
        tpl: &'a Template,
        opts: &FitOptions,
    ) -> Result<Self> {
        if sx.data.dim() != sy.data.dim() || sx.x != sy.x || sx.y != sy.y {
            return Err(AnalysisError::BadInput {
                name: "sy",
                reason: "Sx and Sy images must have the same shape and axes".into(),
            });
        }
        if sx.rows() == 0 || sx.cols() == 0 {
            return Err(AnalysisError::BadInput {
                name: "sx",
                reason: "empty image".into(),
            });
        }
        check_axis("sx.x", &sx.x, 1)?;
        check_axis("sx.y", &sx.y, 1)?;
        let tr = tpl.truncation();
        if tr > opts.max_truncation {
            let ((u0, u1), (v0, v1)) = tpl.extent();
            return Err(AnalysisError::TemplateCoverage(format!(
                "the template is truncated: its border value is {:.1}% of its peak (allowed {:.1}%); it covers only u ∈ [{u0}, {u1}], v ∈ [{v0}, {v1}] µm, build it wider",
                100.0 * tr,
                100.0 * opts.max_truncation
            )));
        }
        let ch_data = [
            sx.data.iter().copied().collect::<Vec<_>>(),
            sy.data.iter().copied().collect::<Vec<_>>(),
        ];
        let chans = opts.channels.list();
        let m: usize = chans
            .iter()
            .map(|&c| ch_data[c].iter().filter(|v| v.is_finite()).count())
            .sum();
        if m == 0 {
            return Err(AnalysisError::BadInput {
                name: "sx, sy",
                reason: "no finite pixel in the fitted channels".into(),
            });
        }
        let (ax, ay) = (AxisMap::new(&sx.x), AxisMap::new(&sy.y));
        let (px, py) = (ax.h.abs(), ay.h.abs());
        let (px, py) = (
            if px > 0.0 { px } else { py },
            if py > 0.0 { py } else { px },
        );
        let (px, py) = if px > 0.0 {
            (px, py)
        } else {
            (tpl.grid.h, tpl.grid.h)
        };
        let area = sx.cols() as f64 * px * sx.rows() as f64 * py;
        let mask = [0, 1].map(|ch| {
            let on = chans.contains(&ch);
            ch_data[ch]
                .iter()
                .map(|v| if on && v.is_finite() { 1.0 } else { 0.0 })
                .collect::<Vec<f64>>()
        });
        let g = &tpl.grid;
        let planes = (g.interp == crate::optics::grid::Interp::Cubic && g.nu >= 2 && g.nv >= 2)
            .then(|| TplPlanes::new(g));
        Ok(Self {
            tpl,
            x: sx.x.clone(),
            y: sx.y.clone(),
            ax,
            ay,
            ch_data,
            chans,
            m,
            area,
            w0: opts.w0_um,
            min_sep: opts.min_separation * opts.w0_um,
            inv_f: 1.0 / tpl.norm_factor,
            scratch: std::sync::Mutex::new(std::mem::take(
                &mut *SCRATCH_POOL
                    .lock()
                    .unwrap_or_else(std::sync::PoisonError::into_inner),
            )),
            mask,
            planes,
            #[cfg(test)]
            reference: false,
        })
    }

    pub(super) fn nx(&self) -> usize {
        self.x.len()
    }

    /// Error when the image cannot support `n` beads.
    pub(super) fn check_count(&self, n: usize) -> Result<()> {
        let patch = (self.min_sep.max(0.25 * self.w0)).powi(2);
        let by_area = (self.area / patch).floor() as usize;
        let by_data = self.m.saturating_sub(1) / 3;
        let nmax = by_area.min(by_data);
        if n > nmax {
            return Err(AnalysisError::TooManyBeads(format!(
                "n = {n} beads but this image supports at most {nmax} (area {:.3} µm² / ({:.3} µm)² per bead = {by_area}; {} residuals allow {by_data} beads of 3 parameters)",
                self.area,
                patch.sqrt(),
                self.m
            )));
        }
        Ok(())
    }

    /// True when a bead at (x, y) has template support overlapping the image.
    pub(super) fn reaches(&self, x: f64, y: f64) -> bool {
        let ((u0, u1), (v0, v1)) = self.tpl.extent();
        !self.ax.range(x + u0, x + u1).is_empty() && !self.ay.range(y + v0, y + v1).is_empty()
    }

    /// Each bead's window at parameters p = [C, x, y]ᵢ: the pixel rows and columns within the
    /// template's extent around it.
    pub(super) fn windows(&self, p: &[f64]) -> Vec<Shape> {
        let ((u0, u1), (v0, v1)) = self.tpl.extent();
        p.chunks(3)
            .map(|b| {
                (
                    self.ay.range(b[2] + v0, b[2] + v1),
                    self.ax.range(b[1] + u0, b[1] + u1),
                )
            })
            .collect()
    }

    /// Adds the model of a tile's windows (`items`, `wins`; see [`FitData::sample_tile`]) to
    /// `out`, the tile's images of the channels `chans` (tw columns), beads in index order at
    /// every pixel; beads of weight zero add nothing.
    pub(super) fn add_model(
        &self,
        p: &[f64],
        items: &[TileItem],
        wins: &[Window],
        chans: &[usize],
        tw: usize,
        out: &mut [Vec<f64>; 2],
    ) {
        for ((i, _, _), w) in items.iter().zip(wins) {
            let wi = p[3 * i] * self.inv_f;
            if wi == 0.0 {
                continue;
            }
            let nc = w.cols.len();
            for &ch in chans {
                let plane = w.plane(3 * ch);
                for (rr, r) in w.rows.clone().enumerate() {
                    let base = r * tw + w.cols.start;
                    let m = &mut out[ch][base..base + nc];
                    for (m, s) in m.iter_mut().zip(&plane[rr * nc..(rr + 1) * nc]) {
                        *m += wi * s;
                    }
                }
            }
        }
    }

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

    /// A tile buffer from the fit's pool (or a new one).
    pub(super) fn scratch_take(&self) -> Scratch {
        self.scratch
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .pop()
            .unwrap_or_default()
    }

    /// Back to the pool.
    pub(super) fn scratch_give(&self, sc: Scratch) {
        self.scratch
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .push(sc);
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
            self.sample_window(
                p[3 * i + 1],
                p[3 * i + 2],
                rows.clone(),
                cols.clone(),
                mask,
                s,
            );
            wins.push(Window {
                rows: rows.start - tr.start..rows.end - tr.start,
                cols: cols.start - tc.start..cols.end - tc.start,
                s,
            });
        }
        wins
    }

    /// Samples of the template around a bead at (bx, by) µm over the window `rows` × `cols`
    /// into `out`: six planes of rows.len() × cols.len() (see [`FitData::accumulate`]), zero
    /// where `mask` is 0 (the fit's mask: the channel's datum invalid or the channel not
    /// fitted; None: nowhere). Every element of `out` is written. Derivatives in
    /// instrument units per µm, as [`Grid2::eval_grad`](crate::optics::grid::Grid2::eval_grad).
    ///
    /// On x86-64 CPUs with AVX2 the same code runs compiled for AVX2 + FMA (runtime dispatch;
    /// the binary still runs on any x86-64 and other targets). No multiply–add is contracted
    /// into an FMA (Rust does not contract without `mul_add`), so both paths round alike.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn sample_window(
        &self,
        bx: f64,
        by: f64,
        rows: std::ops::Range<usize>,
        cols: std::ops::Range<usize>,
        mask: Option<&[Vec<f64>; 2]>,
        out: &mut [f64],
    ) {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
        {
            // SAFETY: the CPU supports the features the function is compiled for (checked just
            // above).
            unsafe { self.sample_window_avx2(bx, by, rows, cols, mask, out) };
            return;
        }
        self.sample_window_impl::<false>(bx, by, rows, cols, mask, out)
    }

    /// [`FitData::sample_window`] compiled for AVX2 + FMA.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    pub(super) fn sample_window_avx2(
        &self,
        bx: f64,
        by: f64,
        rows: std::ops::Range<usize>,
        cols: std::ops::Range<usize>,
        mask: Option<&[Vec<f64>; 2]>,
        out: &mut [f64],
    ) {
        self.sample_window_impl::<true>(bx, by, rows, cols, mask, out)
    }

    /// `SIMD`: use the AVX2 kernels (only from [`FitData::sample_window_avx2`]).
    #[inline(always)]
    pub(super) fn sample_window_impl<const SIMD: bool>(
        &self,
        bx: f64,
        by: f64,
        rows: std::ops::Range<usize>,
        cols: std::ops::Range<usize>,
        mask: Option<&[Vec<f64>; 2]>,
        out: &mut [f64],
    ) {
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

    /// The pixel-major accumulation used before issue 20 (one `eval_grad` per bead and pixel,
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

    /// Model images of Sx and Sy (all pixels, whatever was fitted) for beads p, sampled as in
    /// [`FitData::accumulate`] (the separable stencil; equal to
    /// [`Template::render`]'s to rounding).
    pub(super) fn model(&self, p: &[f64]) -> [Array2<f64>; 2] {
        use rayon::prelude::*;
        let (ny, nx) = (self.y.len(), self.nx());
        if self.planes.is_none() {
            let [a, b, _] = self.tpl.render(
                &p.chunks(3)
                    .map(|b| (b[1], b[2], b[0] * self.inv_f))
                    .collect::<Vec<_>>(),
                &self.x,
                &self.y,
            );
            return [a, b];
        }
        let shapes = self.windows(p);
        // Tile by tile (as `accumulate`), each pixel the sum of the beads in index order.
        let tiles = tiles(ny, nx);
        let parts: Vec<[Vec<f64>; 2]> = tiles
            .par_iter()
            .map(|(tr, tc)| {
                let (th, tw) = (tr.len(), tc.len());
                let mut o = [vec![0.0; th * tw], vec![0.0; th * tw]];
                let items = tile_items(&shapes, tr, tc);
                if items.is_empty() {
                    return o;
                }
                let mut sc = self.scratch_take();
                let wins = self.sample_tile(p, &items, tr, tc, None, &mut sc.0);
                self.add_model(p, &items, &wins, &[0, 1], tw, &mut o);
                drop(wins);
                self.scratch_give(sc);
                o
            })
            .collect();
        let mut out = [Array2::zeros((ny, nx)), Array2::zeros((ny, nx))];
        for ((tr, tc), part) in tiles.iter().zip(&parts) {
            for (ch, o) in out.iter_mut().enumerate() {
                for (rr, r) in tr.clone().enumerate() {
                    for (cc, c) in tc.clone().enumerate() {
                        o[[r, c]] = part[ch][rr * tc.len() + cc];
                    }
                }
            }
        }
        out
    }

    /// One LM run from `init` (see [`levenberg_marquardt`]).
    pub(super) fn run_lm(&self, init: &[BeadInit], opts: &FitOptions) -> Result<RawFit> {
        let x0: Vec<f64> = init.iter().flat_map(|b| [b.weight, b.x, b.y]).collect();
        let tol = Tolerances {
            ftol: opts.ftol,
            xtol: opts.xtol,
            gtol: opts.gtol,
            patience: opts.patience,
        };
        let raw = levenberg_marquardt(|p| self.accumulate(p), x0, &tol);
        if raw.p.iter().any(|v| !v.is_finite()) {
            return Err(AnalysisError::Failed(format!(
                "the optimiser returned non-finite parameters ({})",
                raw.reason
            )));
        }
        Ok(raw)
    }

    /// LM fit with all degeneracy checks (see the module docs).
    pub(super) fn fit_with_degeneracy(
        &self,
        init: Vec<BeadInit>,
        opts: &FitOptions,
    ) -> Result<FitResult> {
        let mut res = self.fit_merge_close(init, opts, Vec::new())?;
        let lim = opts.resolve_separation * self.w0;
        'outer: while opts.merge_degenerate && lim > 0.0 && res.beads.len() > 1 {
            let b = &res.beads;
            let mut pairs: Vec<(usize, usize, f64)> = Vec::new();
            for i in 0..b.len() {
                for j in i + 1..b.len() {
                    let d = (b[i].x - b[j].x).hypot(b[i].y - b[j].y);
                    if d < lim {
                        pairs.push((i, j, d));
                    }
                }
            }
            pairs.sort_by(|a, b| a.2.total_cmp(&b.2));
            for (i, j, d) in pairs {
                let (a, c) = (b[i], b[j]);
                let mut init: Vec<BeadInit> = b
                    .iter()
                    .enumerate()
                    .filter(|(k, _)| *k != i && *k != j)
                    .map(|(_, x)| BeadInit {
                        x: x.x,
                        y: x.y,
                        weight: x.weight,
                    })
                    .collect();
                init.push(merge_pair(
                    BeadInit {
                        x: a.x,
                        y: a.y,
                        weight: a.weight,
                    },
                    BeadInit {
                        x: c.x,
                        y: c.y,
                        weight: c.weight,
                    },
                ));
                let mut deg = res.degeneracies.clone();
                let alt0 = self.fit_merge_close(init, opts, Vec::new())?;
                let insignificant = |x: &Bead| {
                    x.weight.abs() < 1e-9 || x.weight_err.is_some_and(|e| x.weight.abs() < 2.0 * e)
                };
                if alt0.bic <= res.bic || insignificant(&a) || insignificant(&c) {
                    deg.push(Degeneracy::Unresolved {
                        a: [a.x, a.y, a.weight],
                        b: [c.x, c.y, c.weight],
                        distance_um: d,
                        delta_bic: res.bic - alt0.bic,
                    });
                    deg.extend(alt0.degeneracies.iter().cloned());
                    let total = res.total_evaluations + alt0.total_evaluations;
                    res = alt0;
                    res.degeneracies = deg;
                    res.total_evaluations = total;
                    continue 'outer;
                }
            }
            break;
        }
        // Weights consistent with zero.
        let extra: Vec<Degeneracy> = res
            .beads
            .iter()
            .filter(|b| {
                b.weight.abs() < 1e-9 || b.weight_err.is_some_and(|e| b.weight.abs() < 2.0 * e)
            })
            .map(|b| Degeneracy::Insignificant {
                x: b.x,
                y: b.y,
                weight: b.weight,
                weight_err: b.weight_err,
            })
            .collect();
        res.degeneracies.extend(extra);
        Ok(res)
    }

    /// LM fit with merging of pairs closer than min_separation·w0 and dropping of beads out of
    /// reach, then the statistics.
    pub(super) fn fit_merge_close(
        &self,
        init: Vec<BeadInit>,
        opts: &FitOptions,
        mut degeneracies: Vec<Degeneracy>,
    ) -> Result<FitResult> {
        let mut beads = init;
        let mut total_eval = 0;
        let mut raw;
        loop {
            raw = self.run_lm(&beads, opts)?;
            total_eval += raw.evaluations;
            let cur: Vec<BeadInit> = raw
                .p
                .chunks(3)
                .map(|b| BeadInit {
                    weight: b[0],
                    x: b[1],
                    y: b[2],
                })
                .collect();
            // Beads out of reach.
            let (keep, gone): (Vec<BeadInit>, Vec<BeadInit>) =
                cur.iter().partition(|b| self.reaches(b.x, b.y));
            if !gone.is_empty() && !keep.is_empty() {
                for b in &gone {
                    degeneracies.push(Degeneracy::BeadOutside {
                        x: b.x,
                        y: b.y,
                        weight: b.weight,
                    });
                }
                beads = keep;
                continue;
            }
            // Closest pair below the separation limit.
            let mut pair: Option<(usize, usize, f64)> = None;
            for i in 0..cur.len() {
                for j in i + 1..cur.len() {
                    let d = (cur[i].x - cur[j].x).hypot(cur[i].y - cur[j].y);
                    if d < self.min_sep && pair.is_none_or(|p| d < p.2) {
                        pair = Some((i, j, d));
                    }
                }
            }
            if let Some((i, j, d)) = pair {
                let (a, b) = (cur[i], cur[j]);
                degeneracies.push(Degeneracy::CloseBeads {
                    a: [a.x, a.y, a.weight],
                    b: [b.x, b.y, b.weight],
                    distance_um: d,
                    merged: opts.merge_degenerate,
                });
                if opts.merge_degenerate {
                    let merged = merge_pair(a, b);
                    let mut next: Vec<BeadInit> = cur
                        .iter()
                        .enumerate()
                        .filter(|(k, _)| *k != i && *k != j)
                        .map(|(_, b)| *b)
                        .collect();
                    next.push(merged);
                    beads = next;
                    continue;
                }
            }
            break;
        }
        // Statistics at the solution.
        let p = &raw.p;
        let nb = p.len() / 3;
        // The optimiser's last accepted evaluation is the one at the solution.
        let (rss, jtj) = (raw.rss, &raw.jtj);
        let np = p.len();
        let dof = self.m.saturating_sub(np);
        let (sigma, est) = match opts.sigma {
            Some(s) => (s, false),
            None => ((rss / dof.max(1) as f64).sqrt(), true),
        };
        let chi2 = if sigma > 0.0 {
            rss / (sigma * sigma)
        } else {
            0.0
        };
        let mf = self.m as f64;
        let bic = match opts.sigma {
            Some(_) => chi2 + np as f64 * mf.ln(),
            None => mf * (rss.max(1e-300) / mf).ln() + np as f64 * mf.ln(),
        };
        // The condition number and the covariance are independent O(n³) steps: computed side by
        // side (the covariance is dropped if the problem is ill-conditioned).
        let (condition, cov) = rayon::join(
            || scaled_condition(jtj),
            || {
                jtj.clone()
                    .cholesky()
                    .map(|c| c.inverse() * (sigma * sigma))
            },
        );
        let ill = !(condition <= opts.cond_limit);
        if ill {
            degeneracies.push(Degeneracy::IllConditioned { condition });
        }
        let cov = if ill { None } else { cov };
        let beads_out: Vec<Bead> = (0..nb)
            .map(|i| {
                let e = |k: usize| {
                    cov.as_ref()
                        .map(|c| c[(3 * i + k, 3 * i + k)].max(0.0).sqrt())
                };
                Bead {
                    weight: p[3 * i],
                    x: p[3 * i + 1],
                    y: p[3 * i + 2],
                    weight_err: e(0),
                    x_err: e(1),
                    y_err: e(2),
                    x_crlb: None,
                    y_crlb: None,
                    weight_crlb: None,
                }
            })
            .collect();
        let [msx, msy] = self.model(p);
        let shape = msx.dim();
        let dsx = Array2::from_shape_vec(shape, self.ch_data[0].clone()).expect("shape");
        let dsy = Array2::from_shape_vec(shape, self.ch_data[1].clone()).expect("shape");
        let img = |a: Array2<f64>| Image::new(a, self.x.clone(), self.y.clone());
        Ok(FitResult {
            beads: beads_out,
            residual_sx: img(&dsx - &msx),
            residual_sy: img(&dsy - &msy),
            model_sx: img(msx),
            model_sy: img(msy),
            rss,
            chi2,
            dof,
            n_residuals: self.m,
            sigma,
            sigma_estimated: est,
            bic,
            iterations: raw.iterations,
            evaluations: raw.evaluations,
            total_evaluations: total_eval,
            status: raw.status,
            reason: raw.reason,
            condition,
            degeneracies,
            history: vec![],
            warnings: vec![],
        })
    }
}

/// One bead's window (pixel rows and columns within the template's extent around it) and its
/// template samples there, row-major.
pub(super) struct Window<'s> {
    rows: std::ops::Range<usize>,
    cols: std::ops::Range<usize>,
    /// Six planes of rows × cols samples (see [`FitData::accumulate`]).
    s: &'s [f64],
}

impl Window<'_> {
    /// Σ over the window of (Jₓ·J_y, Jₓ·e) for the three planes of each fitted channel
    /// (unscaled; see [`FitData::accumulate`]), e the residual images.
    pub(super) fn own_sums(
        &self,
        res: &[Vec<f64>; 2],
        chans: &[usize],
        nx: usize,
    ) -> ([[f64; 3]; 3], [f64; 3]) {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
        {
            // SAFETY: the CPU supports the features the function is compiled for.
            return unsafe { self.own_sums_avx2(res, chans, nx) };
        }
        self.own_sums_impl(res, chans, nx)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    pub(super) fn own_sums_avx2(
        &self,
        res: &[Vec<f64>; 2],
        chans: &[usize],
        nx: usize,
    ) -> ([[f64; 3]; 3], [f64; 3]) {
        self.own_sums_impl(res, chans, nx)
    }

    #[inline(always)]
    pub(super) fn own_sums_impl(
        &self,
        res: &[Vec<f64>; 2],
        chans: &[usize],
        nx: usize,
    ) -> ([[f64; 3]; 3], [f64; 3]) {
        let nc = self.cols.len();
        let mut a = [[0.0; 3]; 3];
        let mut g = [0.0; 3];
        for &ch in chans {
            let pl = [
                self.plane(3 * ch),
                self.plane(3 * ch + 1),
                self.plane(3 * ch + 2),
            ];
            for (rr, r) in self.rows.clone().enumerate() {
                let base = r * nx + self.cols.start;
                let e = &res[ch][base..base + nc];
                let row = |k: usize| &pl[k][rr * nc..(rr + 1) * nc];
                let (aa, gg) = dot_sym([row(0), row(1), row(2)], e);
                for x in 0..3 {
                    g[x] += gg[x];
                    for y in 0..3 {
                        a[x][y] += aa[x][y];
                    }
                }
            }
        }
        (a, g)
    }

    /// Σ over the overlap of windows a and b of aₓ·b_y for the three planes of each fitted
    /// channel (unscaled).
    pub(super) fn pair_sums(a: &Self, b: &Self, chans: &[usize]) -> [[f64; 3]; 3] {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
        {
            // SAFETY: the CPU supports the features the function is compiled for.
            return unsafe { Self::pair_sums_avx2(a, b, chans) };
        }
        Self::pair_sums_impl(a, b, chans)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    pub(super) fn pair_sums_avx2(a: &Self, b: &Self, chans: &[usize]) -> [[f64; 3]; 3] {
        Self::pair_sums_impl(a, b, chans)
    }

    #[inline(always)]
    pub(super) fn pair_sums_impl(a: &Self, b: &Self, chans: &[usize]) -> [[f64; 3]; 3] {
        let rows = a.rows.start.max(b.rows.start)..a.rows.end.min(b.rows.end);
        let cols = a.cols.start.max(b.cols.start)..a.cols.end.min(b.cols.end);
        let (nca, ncb) = (a.cols.len(), b.cols.len());
        let mut blk = [[0.0; 3]; 3];
        for &ch in chans {
            for r in rows.clone() {
                let oa = (r - a.rows.start) * nca + (cols.start - a.cols.start);
                let ob = (r - b.rows.start) * ncb + (cols.start - b.cols.start);
                let n = cols.len();
                let ra = [0, 1, 2].map(|k| &a.plane(3 * ch + k)[oa..oa + n]);
                let rb = [0, 1, 2].map(|k| &b.plane(3 * ch + k)[ob..ob + n]);
                let bb = dot_block(ra, rb);
                for x in 0..3 {
                    for y in 0..3 {
                        blk[x][y] += bb[x][y];
                    }
                }
            }
        }
        blk
    }

    /// Plane k: 3·channel + (0 value, 1 ∂/∂u, 2 ∂/∂v).
    pub(super) fn plane(&self, k: usize) -> &[f64] {
        let n = self.s.len() / 6;
        &self.s[k * n..(k + 1) * n]
    }
}

/// The template's Sx and Sy node values, interleaved per node ([Sx, Sy]) in row-major order,
/// padded with `PAD` zero nodes on every side so that a cubic stencil reaching one node past the
/// grid (as [`Grid2::grad_stencil_u`](crate::optics::grid::Grid2::grad_stencil_u) allows) reads
/// zeros without a bounds test.
pub(super) struct TplPlanes {
    stride: usize,
    rows: usize,
    data: Vec<[f64; 2]>,
}

impl TplPlanes {
    const PAD: usize = 2;

    pub(super) fn new(g: &crate::optics::grid::Grid2) -> Self {
        let stride = g.nu + 2 * Self::PAD;
        let rows = g.nv + 2 * Self::PAD;
        let mut data = vec![[0.0; 2]; stride * rows];
        for j in 0..g.nv {
            for i in 0..g.nu {
                let n = g.data[j * g.nu + i];
                data[(j + Self::PAD) * stride + i + Self::PAD] = [n[0], n[1]];
            }
        }
        Self { stride, rows, data }
    }

    /// Nodes `first..first + width` of node row `j` (indices may run up to `PAD` past the grid:
    /// zeros; beyond that the row is empty and reads as zeros).
    pub(super) fn row(&self, j: isize, first: isize, width: usize) -> &[[f64; 2]] {
        let pad = Self::PAD as isize;
        let (jj, ii) = (j + pad, first + pad);
        if jj < 0 || jj as usize >= self.rows || ii < 0 || ii as usize + width > self.stride {
            // Outside the padded grid (cannot happen for the stencils of `grad_stencil_*`).
            return &[];
        }
        let at = jj as usize * self.stride + ii as usize;
        &self.data[at..at + width]
    }
}

/// Dot products of three rows `a` with three rows `b` (all of one length): Σ aₓ·b_y. Four
/// accumulators per sum (one 256-bit vector with AVX2).
#[inline(always)]
pub(super) fn dot_block(a: [&[f64]; 3], b: [&[f64]; 3]) -> [[f64; 3]; 3] {
    const L: usize = 4;
    let n = a[0].len();
    let (a0, a1, a2) = (&a[0][..n], &a[1][..n], &a[2][..n]);
    let (b0, b1, b2) = (&b[0][..n], &b[1][..n], &b[2][..n]);
    let mut m = [[[0.0f64; L]; 3]; 3];
    let it = a0
        .chunks_exact(L)
        .zip(a1.chunks_exact(L))
        .zip(a2.chunks_exact(L))
        .zip(
            b0.chunks_exact(L)
                .zip(b1.chunks_exact(L))
                .zip(b2.chunks_exact(L)),
        );
    for (((x0, x1), x2), ((y0, y1), y2)) in it {
        let av = [x0, x1, x2];
        let bv = [y0, y1, y2];
        for x in 0..3 {
            for y in 0..3 {
                for l in 0..L {
                    m[x][y][l] += av[x][l] * bv[y][l];
                }
            }
        }
    }
    let mut out = [[0.0; 3]; 3];
    for x in 0..3 {
        for y in 0..3 {
            let s = &m[x][y];
            out[x][y] = (s[0] + s[1]) + (s[2] + s[3]);
            for l in n - n % L..n {
                out[x][y] += a[x][l] * b[y][l];
            }
        }
    }
    out
}

/// For one bead's rows a (value, ∂/∂u, ∂/∂v) and the residual row e: (Σ aₓ·a_y, Σ aₓ·e), with
/// four accumulators per sum.
#[inline(always)]
pub(super) fn dot_sym(a: [&[f64]; 3], e: &[f64]) -> ([[f64; 3]; 3], [f64; 3]) {
    const L: usize = 4;
    let n = a[0].len();
    let (a0, a1, a2, e) = (&a[0][..n], &a[1][..n], &a[2][..n], &e[..n]);
    // Upper triangle 00 01 02 11 12 22, then the gradient.
    let mut m = [[0.0f64; L]; 6];
    let mut g = [[0.0f64; L]; 3];
    let it = a0
        .chunks_exact(L)
        .zip(a1.chunks_exact(L))
        .zip(a2.chunks_exact(L))
        .zip(e.chunks_exact(L));
    for (((x0, x1), x2), ee) in it {
        for l in 0..L {
            m[0][l] += x0[l] * x0[l];
            m[1][l] += x0[l] * x1[l];
            m[2][l] += x0[l] * x2[l];
            m[3][l] += x1[l] * x1[l];
            m[4][l] += x1[l] * x2[l];
            m[5][l] += x2[l] * x2[l];
            g[0][l] += x0[l] * ee[l];
            g[1][l] += x1[l] * ee[l];
            g[2][l] += x2[l] * ee[l];
        }
    }
    let sum = |s: &[f64; L]| (s[0] + s[1]) + (s[2] + s[3]);
    let mut t = m.map(|s| sum(&s));
    let mut go = g.map(|s| sum(&s));
    for l in n - n % L..n {
        t[0] += a0[l] * a0[l];
        t[1] += a0[l] * a1[l];
        t[2] += a0[l] * a2[l];
        t[3] += a1[l] * a1[l];
        t[4] += a1[l] * a2[l];
        t[5] += a2[l] * a2[l];
        go[0] += a0[l] * e[l];
        go[1] += a1[l] * e[l];
        go[2] += a2[l] * e[l];
    }
    (
        [[t[0], t[1], t[2]], [t[1], t[3], t[4]], [t[2], t[4], t[5]]],
        go,
    )
}
