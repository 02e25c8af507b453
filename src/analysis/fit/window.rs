//! One bead's window of template samples and the template's node planes (the separable
//! sampler's data), with the dot products of their rows: shared by the problem (`problem.rs`)
//! and the normal equations (`normal.rs`), importing neither.

/// Where a bead's window is sampled: the bead at (`bx`, `by`) µm, over the image's pixel
/// `rows` × `cols` (see [`FitData::sample_window`]).
pub(super) struct WindowAt {
    pub(super) bx: f64,
    pub(super) by: f64,
    pub(super) rows: std::ops::Range<usize>,
    pub(super) cols: std::ops::Range<usize>,
}

/// One bead's window (pixel rows and columns within the template's extent around it) and its
/// template samples there, row-major.
pub(super) struct Window<'s> {
    pub(super) rows: std::ops::Range<usize>,
    pub(super) cols: std::ops::Range<usize>,
    /// Six planes of rows × cols samples (see [`FitData::accumulate`]).
    pub(super) s: &'s [f64],
}

/// The sums of a window's normal equations: JᵀJ over its three planes (3×3) and Jᵀe (3).
pub(super) type Sums = ([[f64; 3]; 3], [f64; 3]);

impl Window<'_> {
    /// Σ over the window of (Jₓ·J_y, Jₓ·e) for the three planes of each fitted channel
    /// (unscaled; see [`FitData::accumulate`]), e the residual images.
    pub(super) fn own_sums(&self, res: &[Vec<f64>; 2], chans: &[usize], nx: usize) -> Sums {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
        {
            // SAFETY: the CPU supports the features the function is compiled for.
            return unsafe { self.own_sums_avx2(res, chans, nx) };
        }
        self.own_sums_impl(res, chans, nx)
    }

    #[inline(always)]
    pub(super) fn own_sums_impl(&self, res: &[Vec<f64>; 2], chans: &[usize], nx: usize) -> Sums {
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
pub(super) fn dot_sym(a: [&[f64]; 3], e: &[f64]) -> Sums {
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
