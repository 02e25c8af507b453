//! Precomputed single-scatterer response (paper Sec. 4.1: images are sums of single-scatterer
//! responses), so that rendering a scene costs one interpolation per scatterer and pixel instead
//! of an aperture integral.
//!
//! A plane of the response at axial displacement z is computed for all (x, y) nodes at once: the
//! phase Ψ of every cone node is separable, e^{iΨ} = e^{i(kz − φ_G − kz cosθ)} ·
//! e^{i(k x²/2R − k x u)} · e^{i(k y²/2R − k y v)}, and so is the Gaussian envelope, so a plane is
//! two real matrix products (Nx × K)(K × 3Ny) over the K cone nodes.
//!
//! Planes are laid on a z grid (spacing `hz`) and built lazily, cached, and interpolated in z by
//! the same cubic convolution as in x and y. Each plane spans ±3.5 w(z) (envelope truncated at
//! e^{−12.25} ≈ 5e-6 of its peak).

use super::grid::{Grid2, Interp};
use super::params::OpticsError;
use super::rayleigh::Detection;
use ndarray::Array2;
use std::collections::HashMap;
use std::sync::{Arc, Mutex};

/// Envelope truncation radius in units of the beam radius w(z).
pub const SUPPORT_W: f64 = 3.5;

/// Accuracy knobs of a model template.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct TemplateSpec {
    /// Lateral node spacing, µm.
    pub h: f64,
    /// Axial plane spacing, µm.
    pub hz: f64,
    pub interp: Interp,
}

impl Default for TemplateSpec {
    fn default() -> Self {
        Self {
            h: 0.02,
            hz: 0.05,
            interp: Interp::Cubic,
        }
    }
}

/// The response per unit polarisability (multiply by α in µm³) on lazily built z planes.
pub struct ModelTemplate {
    pub det: Arc<Detection>,
    pub spec: TemplateSpec,
    planes: Mutex<HashMap<i64, Arc<Grid2>>>,
}

impl std::fmt::Debug for ModelTemplate {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "ModelTemplate(h = {} µm, hz = {} µm, {} planes)",
            self.spec.h,
            self.spec.hz,
            self.n_planes()
        )
    }
}

impl ModelTemplate {
    pub fn new(det: Arc<Detection>, spec: TemplateSpec) -> Result<Self, OpticsError> {
        super::params::check_range("template h (µm)", spec.h, 1e-4, 0.2)?;
        super::params::check_range("template hz (µm)", spec.hz, 1e-4, 1.0)?;
        Ok(Self {
            det,
            spec,
            planes: Mutex::new(HashMap::new()),
        })
    }

    pub fn n_planes(&self) -> usize {
        self.planes.lock().map(|p| p.len()).unwrap_or(0)
    }

    /// Memory held by the cached planes, bytes.
    pub fn bytes(&self) -> usize {
        self.planes
            .lock()
            .map(|p| p.values().map(|g| g.bytes()).sum())
            .unwrap_or(0)
    }

    /// The plane at z-grid index `iz` (z = iz·hz), built on first use.
    pub fn plane(&self, iz: i64) -> Arc<Grid2> {
        if let Some(p) = self
            .planes
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .get(&iz)
        {
            return p.clone();
        }
        let g = Arc::new(plane_grid(
            &self.det,
            iz as f64 * self.spec.hz,
            self.spec.h,
            self.spec.interp,
        ));
        self.planes
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .entry(iz)
            .or_insert(g)
            .clone()
    }

    /// Build all planes covering z ∈ [z_lo, z_hi] now (so timing and memory are predictable).
    pub fn prepare(&self, z_lo: f64, z_hi: f64) {
        let (a, b) = self.z_index_range(z_lo, z_hi);
        for iz in a..=b {
            self.plane(iz);
        }
    }

    fn z_index_range(&self, z_lo: f64, z_hi: f64) -> (i64, i64) {
        let hz = self.spec.hz;
        let (lo, hi) = ((z_lo / hz).floor() as i64, (z_hi / hz).ceil() as i64);
        if self.spec.interp == Interp::Cubic {
            (lo - 1, hi + 1)
        } else {
            (lo, hi)
        }
    }

    /// Per-unit-α response at displacement (x, y, z) µm.
    #[inline]
    pub fn eval(&self, x: f64, y: f64, z: f64) -> [f64; 3] {
        let planes = self.planes_for(z);
        let mut out = [0.0; 3];
        for (g, w) in planes.iter() {
            let v = g.eval(x, y);
            for c in 0..3 {
                out[c] += w * v[c];
            }
        }
        out
    }

    /// Planes and weights that interpolate z (one plane when z sits on a node).
    pub fn planes_for(&self, z: f64) -> Vec<(Arc<Grid2>, f64)> {
        z_stencil(z, self.spec.hz, self.spec.interp)
            .into_iter()
            .map(|(iz, w)| (self.plane(iz), w))
            .collect()
    }
}

/// z-grid indices and weights that interpolate axial position `z` from planes every `hz`
/// (one node when z sits on it; two for linear, four for cubic convolution; none for
/// non-finite z). Shared by the Rayleigh and the Mie templates.
pub fn z_stencil(z: f64, hz: f64, interp: Interp) -> Vec<(i64, f64)> {
    if !z.is_finite() {
        return vec![];
    }
    let f = z / hz;
    let i0 = f.floor();
    let t = f - i0;
    let i0 = i0 as i64;
    if t.abs() < 1e-9 {
        return vec![(i0, 1.0)];
    }
    if 1.0 - t < 1e-9 {
        return vec![(i0 + 1, 1.0)];
    }
    match interp {
        Interp::Linear => vec![(i0, 1.0 - t), (i0 + 1, t)],
        Interp::Cubic => {
            let w = crate::optics::grid::keys_weights(t);
            (0..4).map(|j| (i0 - 1 + j as i64, w[j])).collect()
        }
    }
}

/// A plane's beam at axial displacement z (µm) and its grid: (w µm, 1/R 1/µm, Gouy phase rad)
/// of `Detection::beam_at`, then half, n = 2·half + 1 nodes per side every h µm over
/// ±SUPPORT_W·w, from u0 = −half·h (µm).
fn plane_extent(det: &Detection, z: f64, h: f64) -> (f64, f64, f64, usize, usize, f64) {
    let (w, inv_r, gouy) = det.beam_at(z);
    let half = ((SUPPORT_W * w) / h).ceil() as usize;
    (w, inv_r, gouy, half, 2 * half + 1, -(half as f64) * h)
}

/// One plane of the per-unit-α response at axial displacement z (µm), nodes every `h` µm over
/// ±SUPPORT_W·w(z) in x and y; dimensionless signals per unit α (µm⁻³), suppl. S2 (the
/// summed form in `optics::rayleigh`'s module doc, the paper's Sec. 2.1).
///
/// With x = m·h on the grid, every factor of e^{iΨ}·envelope is separable (module doc):
/// * the Gaussian e^{−x²/w²} and the curvature phase e^{ikx²/2R} depend on the x node only:
///   one `exp` and one `sin_cos` per node (not per node and cone node);
/// * the tilt e^{−ikxu} = e^{−iθm} with θ = khu is tabulated per cone node from
///   e^{−iθr} (r < 8) and e^{−i8θq}, so e^{−iθm} = e^{−iθr}·e^{−i8θq} (m = 8q + r) and
///   e^{−iθ(−m)} its conjugate: 2·(8 + half/8 + 1) `sin_cos` per cone node instead of 2n;
/// * the plane is then one real product [EXre | EXim](n × 2K) · [Qim; Qre](2K × 3n).
///
/// Agrees with [`plane_grid_reference`] to rounding (≤ 1e-12 of the plane's peak signal,
/// `tests/optics.rs`).
pub fn plane_grid(det: &Detection, z: f64, h: f64, interp: Interp) -> Grid2 {
    if det.mirror_symmetric {
        if let Some(g) = plane_grid_mirrored(det, z, h, interp) {
            return g;
        }
    }
    let (w, inv_r, gouy, half, n, u0) = plane_extent(det, z, h);
    let k = det.k;
    let kn = det.nodes.len();
    // per x node: e^{−x²/w²} e^{i k x² inv_r/2}
    let env: Vec<(f64, f64)> = (0..n)
        .map(|i| {
            let x = u0 + i as f64 * h;
            let g = (-x * x / (w * w)).exp();
            let (s, c) = (0.5 * k * x * x * inv_r).sin_cos();
            (g * c, g * s)
        })
        .collect();
    // a[i, j] = EXre, a[i, K + j] = EXim; b[j, c·n + i] = Qim, b[K + j, c·n + i] = Qre
    let mut a = Array2::<f64>::zeros((n, 2 * kn));
    let mut b = Array2::<f64>::zeros((2 * kn, 3 * n));
    let amp0 = det.w0 / w;
    let (mut tu, mut tv) = (Vec::with_capacity(half + 1), Vec::with_capacity(half + 1));
    for (j, node) in det.nodes.iter().enumerate() {
        let (sd, cd) = (k * z - gouy - k * z * node.c).sin_cos();
        let d = node.amp * amp0;
        tilt(k * h * node.u, half, &mut tu);
        tilt(k * h * node.v, half, &mut tv);
        for (i, &(er, ei)) in env.iter().enumerate() {
            let (m, neg) = if i >= half {
                (i - half, false)
            } else {
                (half - i, true)
            };
            let (c, s) = tu[m];
            let s = if neg { -s } else { s };
            // (er + i ei)(c + i s)
            a[[i, j]] = er * c - ei * s;
            a[[i, kn + j]] = er * s + ei * c;
            let (c, s) = tv[m];
            let s = if neg { -s } else { s };
            let (re0, im0) = (er * c - ei * s, er * s + ei * c);
            // (cd + i sd)(re0 + i im0)
            let (re, im) = (cd * re0 - sd * im0, cd * im0 + sd * re0);
            for ch in 0..3 {
                let sc = node.s[ch] * d;
                b[[j, ch * n + i]] = sc * im;
                b[[kn + j, ch * n + i]] = sc * re;
            }
        }
    }
    // S = −Im(EX · Q) = −(EXre·Qim + EXim·Qre); rows = x index, cols = (channel, y index)
    let s = a.dot(&b);
    let mut data = vec![[0.0; 3]; n * n];
    for jy in 0..n {
        for ix in 0..n {
            let cell = &mut data[jy * n + ix];
            for ch in 0..3 {
                cell[ch] = -s[[ix, ch * n + jy]];
            }
        }
    }
    Grid2::square(u0, h, n, data, interp)
}

/// e^{−iθm} for m = 0 ..= half as (cos θm, −sin θm), from a two-level table: e^{−iθr}
/// (r < 8) times e^{−i8θq} (m = 8q + r), so 8 + half/8 + 1 `sin_cos` instead of half + 1.
fn tilt(theta: f64, half: usize, out: &mut Vec<(f64, f64)>) {
    const B: usize = 8;
    out.clear();
    let lo: [(f64, f64); B] = std::array::from_fn(|r| {
        let (s, c) = (-theta * r as f64).sin_cos();
        (c, s)
    });
    for q in 0..=half / B {
        let (s8, c8) = (-theta * (B * q) as f64).sin_cos();
        for &(c, s) in &lo {
            if out.len() > half {
                return;
            }
            out.push((c8 * c - s8 * s, c8 * s + s8 * c));
        }
    }
}

/// [`plane_grid`] for a mirror-symmetric cone rule ([`Detection::mirror_symmetric`]): the
/// four mirror images of a node (u, v) sum to
///   Sz: 4 cos(kxu) cos(kyv),  Sx: −4i sin(kxu) cos(kyv),  Sy: −4i cos(kxu) sin(kyv)
/// times the node's P = amp · (w0/w) · e^{i(kz − φ_G − kz cosθ)}, and the plane has the parities
/// Sx odd in x and even in y, Sy even in x and odd in y, Sz even in both; so only the quarter
/// x, y ≥ 0 and a quarter of the nodes enter the products (16× fewer multiply-adds). Then
/// S_c = −Im[g(x) g(y) e^{ik(x² + y²)/2R} T_c(x, y)] as in the module doc (suppl. S2).
/// `None` when the rule is not made of quartets (then the general path runs).
fn plane_grid_mirrored(det: &Detection, z: f64, h: f64, interp: Interp) -> Option<Grid2> {
    let (w, inv_r, gouy, half, n, u0) = plane_extent(det, z, h);
    let k = det.k;
    let quarter: Vec<_> = det
        .nodes
        .iter()
        .filter(|p| p.u > 0.0 && p.v > 0.0)
        .collect();
    if 4 * quarter.len() != det.nodes.len() || quarter.iter().any(|p| p.s != [1.0; 3]) {
        return None;
    }
    let kq = quarter.len();
    let m = half + 1;
    // e^{−x²/w²} e^{i k x² inv_r/2} at x = m·h, m ≥ 0
    let env: Vec<(f64, f64)> = (0..m)
        .map(|i| {
            let x = u0 + (half + i) as f64 * h;
            let g = (-x * x / (w * w)).exp();
            let (s, c) = (0.5 * k * x * x * inv_r).sin_cos();
            (g * c, g * s)
        })
        .collect();
    // cu = [cos kxu | sin kxu] (m × 2K/4); rc = [Pr cos kyv | Pi cos kyv | Pr sin kyv | Pi sin kyv]ᵀ
    let mut cu = Array2::<f64>::zeros((m, 2 * kq));
    let mut rc = Array2::<f64>::zeros((kq, 4 * m));
    let amp0 = det.w0 / w;
    let (mut tu, mut tv) = (Vec::with_capacity(m), Vec::with_capacity(m));
    for (j, node) in quarter.iter().enumerate() {
        let (sd, cd) = (k * z - gouy - k * z * node.c).sin_cos();
        let d = node.amp * amp0;
        let (pr, pi) = (d * cd, d * sd);
        tilt(k * h * node.u, half, &mut tu);
        tilt(k * h * node.v, half, &mut tv);
        for i in 0..m {
            cu[[i, j]] = tu[i].0;
            cu[[i, kq + j]] = -tu[i].1;
            let (c, s) = (tv[i].0, -tv[i].1);
            rc[[j, i]] = pr * c;
            rc[[j, m + i]] = pi * c;
            rc[[j, 2 * m + i]] = pr * s;
            rc[[j, 3 * m + i]] = pi * s;
        }
    }
    let (c_u, s_u) = (
        cu.slice(ndarray::s![.., ..kq]),
        cu.slice(ndarray::s![.., kq..]),
    );
    // zy = [Zr | Zi | Yr | Yi] with Z = Cu P Cvᵀ, Y = Cu P Svᵀ; x = [Xr | Xi] with X = Su P Cvᵀ
    let zy = c_u.dot(&rc);
    let xx = s_u.dot(&rc.slice(ndarray::s![.., ..2 * m]));
    let mut data = vec![[0.0; 3]; n * n];
    for my in 0..m {
        for mx in 0..m {
            // E(x) E(y)
            let (ax, bx) = env[mx];
            let (ay, by) = env[my];
            let (er, ei) = (ax * ay - bx * by, ax * by + bx * ay);
            // T = 4·(Tr + i Ti): Tz = Z, Tx = −iX = Xi − i Xr, Ty = Yi − i Yr
            let t = [
                (xx[[mx, m + my]], -xx[[mx, my]]),
                (zy[[mx, 3 * m + my]], -zy[[mx, 2 * m + my]]),
                (zy[[mx, my]], zy[[mx, m + my]]),
            ];
            let v = t.map(|(tr, ti)| -4.0 * (er * ti + ei * tr));
            for (sx, sy) in [(1.0, 1.0), (-1.0, 1.0), (1.0, -1.0), (-1.0, -1.0)] {
                let ix = (half as f64 + sx * mx as f64) as usize;
                let iy = (half as f64 + sy * my as f64) as usize;
                data[iy * n + ix] = [sx * v[0], sy * v[1], v[2]];
            }
        }
    }
    Some(Grid2::square(u0, h, n, data, interp))
}

/// The reference implementation of [`plane_grid`] (before the speed work): a Gaussian `exp` and two
/// `sin_cos` per (x node, cone node). Kept for the test that holds [`plane_grid`] to it
/// (`tests/optics.rs`) and for the render bench's "before" numbers. Same units and equations.
pub fn plane_grid_reference(det: &Detection, z: f64, h: f64, interp: Interp) -> Grid2 {
    let (w, inv_r, gouy, _, n, u0) = plane_extent(det, z, h);
    let k = det.k;
    let kn = det.nodes.len();
    let coords: Vec<f64> = (0..n).map(|i| u0 + i as f64 * h).collect();
    // ex[i, n] = e^{−x²/w²} e^{i(k x² inv_r/2 − k x u_n)}  (real and imaginary parts)
    let mut ex_re = Array2::<f64>::zeros((n, kn));
    let mut ex_im = Array2::<f64>::zeros((n, kn));
    // q[n, c·N + j] = d_{n,c} · e^{−y²/w²} e^{i(k y² inv_r/2 − k y v_n)}
    let mut q_re = Array2::<f64>::zeros((kn, 3 * n));
    let mut q_im = Array2::<f64>::zeros((kn, 3 * n));
    let amp0 = det.w0 / w;
    for (j, node) in det.nodes.iter().enumerate() {
        let (sd, cd) = (k * z - gouy - k * z * node.c).sin_cos();
        let d = node.amp * amp0;
        for (i, &x) in coords.iter().enumerate() {
            let g = (-x * x / (w * w)).exp();
            let (s, c) = (0.5 * k * x * x * inv_r - k * x * node.u).sin_cos();
            ex_re[[i, j]] = g * c;
            ex_im[[i, j]] = g * s;
            let (s, c) = (0.5 * k * x * x * inv_r - k * x * node.v).sin_cos();
            // (cd + i sd)(c + i s) · g
            let (re, im) = (g * (cd * c - sd * s), g * (cd * s + sd * c));
            for ch in 0..3 {
                let sc = node.s[ch] * d;
                q_re[[j, ch * n + i]] = sc * re;
                q_im[[j, ch * n + i]] = sc * im;
            }
        }
    }
    // S = −Im(EX · Q) = −(EXre·Qim + EXim·Qre); rows = x index, cols = (channel, y index)
    let s = -(ex_re.dot(&q_im) + ex_im.dot(&q_re));
    let mut data = vec![[0.0; 3]; n * n];
    for jy in 0..n {
        for ix in 0..n {
            let cell = &mut data[jy * n + ix];
            for ch in 0..3 {
                cell[ch] = s[[ix, ch * n + jy]];
            }
        }
    }
    Grid2::square(u0, h, n, data, interp)
}
