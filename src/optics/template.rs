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

/// One plane of the per-unit-α response at axial displacement z, nodes every `h` µm over
/// ±SUPPORT_W·w(z) in x and y.
pub fn plane_grid(det: &Detection, z: f64, h: f64, interp: Interp) -> Grid2 {
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
