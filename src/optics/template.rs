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
            let t2 = t * t;
            let t3 = t2 * t;
            let w = [
                0.5 * (-t3 + 2.0 * t2 - t),
                0.5 * (3.0 * t3 - 5.0 * t2 + 2.0),
                0.5 * (-3.0 * t3 + 4.0 * t2 + t),
                0.5 * (t3 - t2),
            ];
            (0..4).map(|j| (i0 - 1 + j as i64, w[j])).collect()
        }
    }
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
    let (w, inv_r, gouy) = det.beam_at(z);
    let half = ((SUPPORT_W * w) / h).ceil() as usize;
    let n = 2 * half + 1;
    let u0 = -(half as f64) * h;
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
    const B: usize = 8;
    let nq = half / B + 1;
    // e^{−iθm}, m = 0 ..= half, for θ = k h u (two-level table)
    let tilt = |theta: f64, out: &mut Vec<(f64, f64)>| {
        out.clear();
        let lo: Vec<(f64, f64)> = (0..B)
            .map(|r| {
                let (s, c) = (-theta * r as f64).sin_cos();
                (c, s)
            })
            .collect();
        for q in 0..nq {
            let (s8, c8) = (-theta * (B * q) as f64).sin_cos();
            for &(c, s) in &lo {
                if out.len() > half {
                    break;
                }
                out.push((c8 * c - s8 * s, c8 * s + s8 * c));
            }
        }
    };
    // a[i, j] = EXre, a[i, K + j] = EXim; b[j, c·n + i] = Qim, b[K + j, c·n + i] = Qre
    let mut a = Array2::<f64>::zeros((n, 2 * kn));
    let mut b = Array2::<f64>::zeros((2 * kn, 3 * n));
    let amp0 = det.w0 / w;
    let (mut tu, mut tv) = (Vec::with_capacity(half + 1), Vec::with_capacity(half + 1));
    for (j, node) in det.nodes.iter().enumerate() {
        let (sd, cd) = (k * z - gouy - k * z * node.c).sin_cos();
        let d = node.amp * amp0;
        tilt(k * h * node.u, &mut tu);
        tilt(k * h * node.v, &mut tv);
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
    Grid2 {
        u0,
        v0: u0,
        h,
        nu: n,
        nv: n,
        data,
        interp,
    }
}

/// The reference implementation of [`plane_grid`] (before issue 20): a Gaussian `exp` and two
/// `sin_cos` per (x node, cone node). Kept for the test that holds [`plane_grid`] to it
/// (`tests/optics.rs`) and for the render bench's "before" numbers. Same units and equations.
pub fn plane_grid_reference(det: &Detection, z: f64, h: f64, interp: Interp) -> Grid2 {
    let (w, inv_r, gouy) = det.beam_at(z);
    let half = ((SUPPORT_W * w) / h).ceil() as usize;
    let n = 2 * half + 1;
    let u0 = -(half as f64) * h;
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
    Grid2 {
        u0,
        v0: u0,
        h,
        nu: n,
        nv: n,
        data,
        interp,
    }
}
