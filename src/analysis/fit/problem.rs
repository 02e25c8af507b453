//! The fit's problem: the images prepared for fitting (channels, masks, axes, the template's
//! node planes), the beads' windows, the tiles and their scratch buffers, and the model images.
//! The normal equations are in `normal.rs`, their AVX2 entry points in `simd.rs`, the
//! degeneracy policy in `degeneracy.rs`.

use super::super::template::Template;
use super::super::{check_axis, AnalysisError, AxisMap, Result};
use super::types::*;
use super::window::{TplPlanes, Window};
use crate::data::Image;
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
}
