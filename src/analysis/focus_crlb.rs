//! The Cramér–Rao bound of the focus: how well an XZ (or YZ) scan of one small object can fix
//! the object's height, and so the best focus z (suppl. S5; the bound of `analysis::crlb`).
//!
//! Model of one channel of the scan: μ(u_i, z_j) = w·M(u_i − u0, z_j − z0) + b, with u the
//! lateral scan coordinate (µm), z the stage height (µm), M the response of a unit object (the
//! reference bead, weight 1) at lateral offset u and height offset z from the focus, (u0, z0)
//! the object's position, w its weight in reference-bead units and b a constant background.
//! Parameters θ = (u0, z0, w, b); ∂μ/∂u0 and ∂μ/∂z0 by central differences of M with a step of
//! 5 nm (M is smooth on the beam's scale of ~0.4 µm laterally and ~1 µm axially), ∂μ/∂w = M,
//! ∂μ/∂b = 1. The response M is supplied by the caller (the simulator's renderer in the same
//! beam, through the script layer): this module does no optics and no I/O.
//!
//! The best focus of the focus search is the object's height z0 (the sensitivity is highest
//! with the object in the focus), so the bound of z0 is the floor under `z_err`.

use super::crlb::Fisher;
use super::{check_above, AnalysisError, Result};

/// Parameters of the focus model, in order.
pub const FOCUS_PARAMS: [&str; 4] = ["lateral position", "height", "weight", "background"];

/// Finite-difference step of the position derivatives, µm.
pub const FOCUS_DIFF_STEP_UM: f64 = 0.005;

/// The bound (1σ floors) of the focus model's parameters.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct FocusBound {
    /// Lateral position, µm.
    pub u: f64,
    /// Height (the best focus), µm.
    pub z: f64,
    /// Weight, reference-bead units.
    pub weight: f64,
    /// Background, the channel's units.
    pub background: f64,
}

/// The unit response along the scan's lateral axis: `row(us, dz)` gives M(u, dz) for every u
/// in `us` (µm) at height offset dz (µm).
pub type UnitRow<'a> = &'a dyn Fn(&[f64], f64) -> Result<Vec<f64>>;

/// The Cramér–Rao bounds of the focus model's parameters from its Fisher information on the
/// grid `us` (columns) × `zs` (rows), µm, every pixel with noise `sigma` (the channel's units),
/// at (u0, z0, w). See the module docs. Errors: bad inputs, an object the scan carries no
/// information about (w = 0, or a scan that misses it).
pub fn focus_crlb(
    us: &[f64],
    zs: &[f64],
    u0: f64,
    z0: f64,
    w: f64,
    sigma: f64,
    row: UnitRow,
) -> Result<FocusBound> {
    check_above("sigma", sigma, 0.0)?;
    super::check_axis("lateral axis", us, 2)?;
    super::check_axis("z axis", zs, 2)?;
    for (name, v) in [("u0", u0), ("z0", z0), ("weight", w)] {
        if !v.is_finite() {
            return Err(AnalysisError::OutOfRange {
                name,
                value: v,
                allowed: "finite".into(),
            });
        }
    }
    let h = FOCUS_DIFF_STEP_UM;
    let shift = |d: f64| us.iter().map(|u| u - u0 + d).collect::<Vec<f64>>();
    let (u_c, u_p, u_m) = (shift(0.0), shift(h), shift(-h));
    let mut f = Fisher::new(4);
    for &z in zs {
        let dz = z - z0;
        let m = row(&u_c, dz)?;
        let mu_p = row(&u_p, dz)?;
        let mu_m = row(&u_m, dz)?;
        let mz_p = row(&u_c, dz + h)?;
        let mz_m = row(&u_c, dz - h)?;
        for i in 0..us.len() {
            // ∂μ/∂u0 = −w ∂M/∂u, ∂μ/∂z0 = −w ∂M/∂z
            let g = [
                -w * (mu_p[i] - mu_m[i]) / (2.0 * h),
                -w * (mz_p[i] - mz_m[i]) / (2.0 * h),
                m[i],
                1.0,
            ];
            f.add(&g, sigma);
        }
    }
    let b = f.bounds(&FOCUS_PARAMS)?;
    Ok(FocusBound {
        u: b[0],
        z: b[1],
        weight: b[2],
        background: b[3],
    })
}

/// Least-squares weight and background of the unit model at (u0, z0) on the image `data`
/// (rows = `zs`, columns = `us`; non-finite pixels skipped): the linear part of the model, for
/// a bound at the object's own weight. Errors: a model with no signal on the grid.
pub fn focus_weight(
    us: &[f64],
    zs: &[f64],
    data: &ndarray::Array2<f64>,
    u0: f64,
    z0: f64,
    row: UnitRow,
) -> Result<(f64, f64)> {
    let uc: Vec<f64> = us.iter().map(|u| u - u0).collect();
    let (mut n, mut sm, mut sd, mut smm, mut smd) = (0.0f64, 0.0, 0.0, 0.0, 0.0);
    for (j, &z) in zs.iter().enumerate() {
        let m = row(&uc, z - z0)?;
        for (i, mi) in m.iter().enumerate() {
            let d = data[[j, i]];
            if !d.is_finite() {
                continue;
            }
            n += 1.0;
            sm += mi;
            sd += d;
            smm += mi * mi;
            smd += mi * d;
        }
    }
    let var = smm - sm * sm / n.max(1.0);
    if !(var > 0.0) {
        return Err(AnalysisError::Failed(
            "focus bound: the object's model has no signal on the scan's grid".into(),
        ));
    }
    let w = (smd - sm * sd / n) / var;
    Ok((w, (sd - w * sm) / n))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A separable Gaussian-derivative stand-in M(u, z) = u·exp(−u²/a² − z²/c²): the bound of
    /// the height follows from the closed form of the Fisher information. With the lateral and
    /// height parameters decoupled by symmetry (an object centred on a symmetric grid) and the
    /// background and weight coupled to neither u0 nor z0 by parity, I_zz = Σ (w ∂M/∂z)²/σ²,
    /// and the bound is 1/√I_zz.
    #[test]
    fn height_bound_equals_the_closed_form_of_a_separable_model() {
        let (a, c) = (0.4, 0.8);
        let m = |u: f64, z: f64| u * (-(u * u) / (a * a) - z * z / (c * c)).exp();
        let row = |us: &[f64], dz: f64| Ok(us.iter().map(|&u| m(u, dz)).collect());
        let us: Vec<f64> = (0..41).map(|i| -1.0 + 0.05 * i as f64).collect();
        let zs: Vec<f64> = (0..33).map(|i| -1.6 + 0.1 * i as f64).collect();
        let (w, sigma) = (2.0, 1e-3);
        let b = focus_crlb(&us, &zs, 0.0, 0.0, w, sigma, &row).unwrap();
        // closed form: ∂M/∂z = −2z/c²·M
        let mut izz = 0.0;
        for &z in &zs {
            for &u in &us {
                let g = w * 2.0 * z / (c * c) * m(u, z);
                izz += g * g / (sigma * sigma);
            }
        }
        let want = 1.0 / izz.sqrt();
        assert!((b.z / want - 1.0).abs() < 1e-3, "{} vs {want}", b.z);
        // scaling: σ doubles the bound, a heavier object (2w) halves the position bounds
        let b2 = focus_crlb(&us, &zs, 0.0, 0.0, w, 2.0 * sigma, &row).unwrap();
        assert!((b2.z / b.z - 2.0).abs() < 1e-9);
        let b3 = focus_crlb(&us, &zs, 0.0, 0.0, 2.0 * w, sigma, &row).unwrap();
        assert!((b3.z / b.z - 0.5).abs() < 1e-9);
        assert!((b3.weight / b.weight - 1.0).abs() < 1e-9);
        // an object in the focus plane of a scan that does not reach it carries less
        let far = focus_crlb(&us, &zs, 0.0, 1.5, w, sigma, &row).unwrap();
        assert!(far.z > 1.5 * b.z, "{} vs {}", far.z, b.z);
        // no object, no information about its height
        let e = focus_crlb(&us, &zs, 0.0, 0.0, 0.0, sigma, &row)
            .unwrap_err()
            .to_string();
        assert!(e.contains("no information about lateral position"), "{e}");
    }

    /// The weight and background of a noise-free image of the model come back exactly.
    #[test]
    fn weight_of_a_model_image_is_recovered() {
        let m = |u: f64, z: f64| u * (-(u * u) / 0.16 - z * z / 0.64).exp();
        let row = |us: &[f64], dz: f64| Ok(us.iter().map(|&u| m(u, dz)).collect());
        let us: Vec<f64> = (0..21).map(|i| -1.0 + 0.1 * i as f64).collect();
        let zs: Vec<f64> = (0..11).map(|i| -1.0 + 0.2 * i as f64).collect();
        let img = ndarray::Array2::from_shape_fn((11, 21), |(j, i)| {
            3.5 * m(us[i] - 0.1, zs[j] - 0.2) + 0.01
        });
        let (w, b) = focus_weight(&us, &zs, &img, 0.1, 0.2, &row).unwrap();
        assert!(
            (w - 3.5).abs() < 1e-12 && (b - 0.01).abs() < 1e-12,
            "{w} {b}"
        );
    }
}
