//! Physical quantities from maximum sensitivities and fit weights (Sec. 3.2, 5, 6).
//!
//! - [`n_corr`]: eq. nCor, the Clausius–Mossotti ratio of object and reference bead.
//! - [`point_object`]: volume and mass of a point-like object (the equations after nCor).
//!   **Note on the paper:** its mass equation reads m_obj/m_rb = (ρ_rb/ρ_obj)·…, the density
//!   ratio inverted; mass = ρ·V gives (ρ_obj/ρ_rb), which is also what reproduces the paper's
//!   own numbers (950 kDa resolution for polystyrene → 1.1 MDa for globular protein, tested).
//!   We implement m_obj = m_rb·(ρ_obj/ρ_rb)·V_obj/V_rb.
//! - [`DiameterCalib`]: fibril diameter d = A·√((∂Sx/∂x)max,corr) (eqs. colDiam, OurColD) with A
//!   = d_bm/√(sens_bm·n_corr) computed from the template's bead model of a cylinder of diameter
//!   d_bm and index n_bm (never the paper's 58.6 nm, which belongs to its instrument).
//! - [`LinDensCalib`]: linear density μ = μ_bm·(ρ_obj/ρ_bm)·sens_corr/(sens_bm·n_corr)
//!   (eq. mtLinDens) in MDa/µm and the protofilament number (110 kDa per 8 nm tubulin dimer →
//!   13.75 MDa/µm per protofilament; the paper rounds to 13.7).
//!
//! Units: diameters nm, volumes nm³, densities g/cm³, masses kDa (or MDa where named), linear
//! densities MDa/µm; sensitivities in reference-bead units (or any units, consistently).

use super::bead_model::{straight_filament_max_sens, BeadModelOptions};
use super::measure::MeasureOptions;
pub use super::scaling::{clausius_mossotti, mass_kda, n_corr, DA_PER_G};
use super::template::{RefBead, Template};
use super::{check_above, check_positive, check_range, AnalysisError, Result};
use serde::{Deserialize, Serialize};

/// Tubulin dimer mass (kDa) and length (nm) (Sec. 6).
pub const TUBULIN_DIMER_KDA: f64 = 110.0;
pub const TUBULIN_DIMER_NM: f64 = 8.0;
/// Linear density of one protofilament, MDa/µm (= 110 kDa / 8 nm = 13.75).
pub const PROTOFILAMENT_MDA_PER_UM: f64 = TUBULIN_DIMER_KDA / TUBULIN_DIMER_NM;
/// Specific volume of globular proteins 0.745 cm³/g → density (g/cm³) (Sec. 3.2).
pub const PROTEIN_DENSITY_G_CM3: f64 = 1.0 / 0.745;
/// Refractive index of dry globular protein (Sec. 3.2, 6).
pub const PROTEIN_N: f64 = 1.587;

/// Volume and mass of a point-like object.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PointObject {
    /// V_obj/V_rb.
    pub volume_ratio: f64,
    pub volume_nm3: f64,
    /// Diameter of a sphere of that volume, nm.
    pub sphere_d_nm: f64,
    pub mass_kda: f64,
    /// 1σ mass uncertainty (kDa) when an uncertainty of the input was given.
    pub mass_err_kda: Option<f64>,
    pub n_corr: f64,
}

/// Volume and mass of a point-like object from its maximum sensitivity (Sec. 3.2):
/// V_obj/V_rb = sens_obj/(n_corr·sens_rb), m_obj = ρ_obj·V_obj. `sens_rb` is the reference
/// bead's maximum sensitivity measured the same way (1 for template-normalised fit weights,
/// `Template::pipeline_max_sens` for maxima read off sensitivity images). `sens_err`: optional
/// 1σ of `sens_obj` (propagated to `mass_err_kda` — the mass resolution).
///
/// Errors: `sens_rb` ≤ 0, an invisible object (n_obj = n_medium), or a sensitivity whose sign
/// contradicts the index contrast (negative volume).
pub fn point_object(
    sens_obj: f64,
    sens_err: Option<f64>,
    sens_rb: f64,
    n_obj: f64,
    density_obj: f64,
    reference: &RefBead,
) -> Result<PointObject> {
    reference.validate()?;
    check_positive(&[("sens_rb", sens_rb), ("density_obj", density_obj)])?;
    if !sens_obj.is_finite() {
        return Err(AnalysisError::OutOfRange {
            name: "sens_obj",
            value: sens_obj,
            allowed: "finite".into(),
        });
    }
    let nc = n_corr(n_obj, reference.n, reference.n_medium)?;
    if nc == 0.0 {
        return Err(AnalysisError::OutOfRange {
            name: "n_obj",
            value: n_obj,
            allowed: format!(
                "n_obj ≠ n_medium = {} (an index-matched object gives no signal)",
                reference.n_medium
            ),
        });
    }
    let ratio = sens_obj / (nc * sens_rb);
    if ratio < 0.0 {
        return Err(AnalysisError::OutOfRange {
            name: "sens_obj",
            value: sens_obj,
            allowed: format!("same sign as the contrast factor n_corr = {nc:.4} (otherwise the volume would be negative)"),
        });
    }
    let v = ratio * reference.volume_nm3();
    let m = mass_kda(v, density_obj);
    let err = sens_err
        .map(|e| (e / (nc * sens_rb)).abs() * mass_kda(reference.volume_nm3(), density_obj));
    Ok(PointObject {
        volume_ratio: ratio,
        volume_nm3: v,
        sphere_d_nm: (6.0 * v / std::f64::consts::PI).cbrt(),
        mass_kda: m,
        mass_err_kda: err,
        n_corr: nc,
    })
}

/// Mass resolution (kDa) implied by a 1σ uncertainty of a fit weight or normalised maximum
/// sensitivity (Sec. 3.2: "we use the uncertainty in the fit … to find the mass resolution").
pub fn mass_resolution_kda(
    sens_err: f64,
    n_obj: f64,
    density_obj: f64,
    reference: &RefBead,
) -> Result<f64> {
    check_above("sens_err", sens_err, 0.0)?;
    let nc = n_corr(n_obj, reference.n, reference.n_medium)?;
    if nc == 0.0 {
        return Err(AnalysisError::OutOfRange {
            name: "n_obj",
            value: n_obj,
            allowed: "n_obj ≠ n_medium".into(),
        });
    }
    Ok(sens_err / nc.abs() * mass_kda(reference.volume_nm3(), density_obj))
}

/// Calibration of fibril diameters (eqs. colDiam, OurColD): d = A·√(sens_corr).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct DiameterCalib {
    /// Prefactor A, nm per √(reference-bead sensitivity units).
    pub a_nm: f64,
    /// Bead-model cylinder: diameter (nm), index; its maximum ∂Sx/∂x along the QPD y-axis.
    pub d_bm_nm: f64,
    pub n_bm: f64,
    pub sens_bm: f64,
    /// Object index and n_corr(n_obj, n_bm).
    pub n_obj: f64,
    pub n_corr: f64,
}

/// The checks shared by the calibrations from a bead-model sensitivity `sens_bm` (of a
/// filament of `d_bm_nm`, index `n_bm`): both positive, and an object of index `n_obj` with
/// positive contrast in the medium (`why` ends that refusal). Returns n_corr (eq. nCor).
fn bead_model_contrast(
    sens_bm: f64,
    d_bm_nm: f64,
    n_bm: f64,
    n_obj: f64,
    n_medium: f64,
    why: &str,
) -> Result<f64> {
    check_positive(&[("sens_bm", sens_bm), ("d_bm_nm", d_bm_nm)])?;
    let nc = n_corr(n_obj, n_bm, n_medium)?;
    if !(nc > 0.0) {
        return Err(AnalysisError::OutOfRange {
            name: "n_obj",
            value: n_obj,
            allowed: format!("n_obj > n_medium = {n_medium}{why}"),
        });
    }
    Ok(nc)
}

impl DiameterCalib {
    /// A from a measured or modelled bead-model sensitivity: A = d_bm/√(sens_bm·n_corr).
    pub fn from_sens_bm(
        sens_bm: f64,
        d_bm_nm: f64,
        n_bm: f64,
        n_obj: f64,
        n_medium: f64,
    ) -> Result<Self> {
        let why = " (a diameter from √sensitivity needs positive contrast)";
        let nc = bead_model_contrast(sens_bm, d_bm_nm, n_bm, n_obj, n_medium, why)?;
        Ok(Self {
            a_nm: d_bm_nm / (sens_bm * nc).sqrt(),
            d_bm_nm,
            n_bm,
            sens_bm,
            n_obj,
            n_corr: nc,
        })
    }

    /// A from the template's bead model: a straight cylinder of diameter `d_bm_nm` and index
    /// `n_bm` along the QPD y-axis, measured with `measure` on pixels of `pixel_um` (the pixel
    /// size of the scans it will be applied to).
    pub fn from_template(
        tpl: &Template,
        n_obj: f64,
        d_bm_nm: f64,
        n_bm: f64,
        pixel_um: f64,
        measure: &MeasureOptions,
        bm: &BeadModelOptions,
    ) -> Result<Self> {
        let sens_bm = straight_filament_max_sens(tpl, d_bm_nm, n_bm, 0.0, pixel_um, measure, bm)?.0;
        Self::from_sens_bm(sens_bm, d_bm_nm, n_bm, n_obj, tpl.reference.n_medium)
    }

    /// Diameter (nm) from a corrected maximum sensitivity. Zero gives 0 nm (nothing detected);
    /// a negative or non-finite sensitivity is an error (no real square root: the value is
    /// noise or background, not a filament).
    pub fn diameter_nm(&self, sens_corr: f64) -> Result<f64> {
        fibril_diameter_nm(sens_corr, self.a_nm)
    }
}

/// d = A·√(sens_corr) (eq. OurColD). Errors for negative/non-finite sensitivity or A ≤ 0.
pub fn fibril_diameter_nm(sens_corr: f64, a_nm: f64) -> Result<f64> {
    check_above("a_nm", a_nm, 0.0)?;
    if !(sens_corr.is_finite() && sens_corr >= 0.0) {
        return Err(AnalysisError::OutOfRange {
            name: "sens_corr",
            value: sens_corr,
            allowed: "sens_corr ≥ 0 (a diameter needs √sensitivity; negative values are background or noise)".into(),
        });
    }
    Ok(a_nm * sens_corr.sqrt())
}

/// Calibration of linear densities (eq. mtLinDens).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LinDensCalib {
    /// Linear density of the bead-model cylinder, MDa/µm (ρ_bm·π d_bm²/4).
    pub mu_bm_mda_um: f64,
    pub d_bm_nm: f64,
    pub density_bm: f64,
    pub sens_bm: f64,
    pub n_obj: f64,
    pub density_obj: f64,
    pub n_corr: f64,
}

impl LinDensCalib {
    /// From a bead-model sensitivity (cylinder of d_bm, n_bm, density_bm along the QPD y-axis).
    #[allow(clippy::too_many_arguments)]
    pub fn from_sens_bm(
        sens_bm: f64,
        d_bm_nm: f64,
        n_bm: f64,
        density_bm: f64,
        n_obj: f64,
        density_obj: f64,
        n_medium: f64,
    ) -> Result<Self> {
        check_positive(&[("density_bm", density_bm), ("density_obj", density_obj)])?;
        let nc = bead_model_contrast(sens_bm, d_bm_nm, n_bm, n_obj, n_medium, "")?;
        let area = std::f64::consts::PI / 4.0 * d_bm_nm * d_bm_nm;
        let mu_bm = mass_kda(area * 1000.0, density_bm) / 1000.0;
        Ok(Self {
            mu_bm_mda_um: mu_bm,
            d_bm_nm,
            density_bm,
            sens_bm,
            n_obj,
            density_obj,
            n_corr: nc,
        })
    }

    /// From the template's bead model (reference material: the template's reference bead).
    pub fn from_template(
        tpl: &Template,
        n_obj: f64,
        density_obj: f64,
        pixel_um: f64,
        measure: &MeasureOptions,
        bm: &BeadModelOptions,
    ) -> Result<Self> {
        let r = tpl.reference;
        let sens_bm = straight_filament_max_sens(tpl, r.d_nm, r.n, 0.0, pixel_um, measure, bm)?.0;
        Self::from_sens_bm(
            sens_bm,
            r.d_nm,
            r.n,
            r.density_g_cm3,
            n_obj,
            density_obj,
            r.n_medium,
        )
    }

    /// μ (MDa/µm) from a corrected maximum sensitivity; negative/non-finite → error.
    pub fn linear_density(&self, sens_corr: f64) -> Result<f64> {
        if !(sens_corr.is_finite() && sens_corr >= 0.0) {
            return Err(AnalysisError::OutOfRange {
                name: "sens_corr",
                value: sens_corr,
                allowed: "sens_corr ≥ 0".into(),
            });
        }
        Ok(
            self.mu_bm_mda_um * (self.density_obj / self.density_bm) * sens_corr
                / (self.sens_bm * self.n_corr),
        )
    }
}

/// Protofilament number implied by a microtubule linear density: (μ/13.75 MDa/µm, rounded).
pub fn protofilaments(mu_mda_um: f64) -> Result<(f64, u32)> {
    check_range("mu_mda_um", mu_mda_um, 0.0, 1e6)?;
    let x = mu_mda_um / PROTOFILAMENT_MDA_PER_UM;
    Ok((x, x.round() as u32))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn n_corr_limits_and_symmetry() {
        assert!((n_corr(1.572, 1.572, 1.333).unwrap() - 1.0).abs() < 1e-15);
        assert_eq!(n_corr(1.333, 1.572, 1.333).unwrap(), 0.0);
        assert!(n_corr(1.30, 1.572, 1.333).unwrap() < 0.0);
        let e = n_corr(1.5, 1.3, 1.333).unwrap_err().to_string();
        assert!(
            e.starts_with("n_ref = 1.3 is out of range: n_ref > n_medium = 1.333"),
            "{e}"
        );
        // Small-contrast limit: CM ≈ 2Δn/(3 n_s)·… so the ratio → Δn_obj/Δn_ref.
        let r = n_corr(1.3331, 1.3332, 1.333).unwrap();
        assert!((r - 0.5).abs() < 1e-3);
    }

    #[test]
    fn reference_mass_and_paper_resolution() {
        let rb = RefBead::default();
        // 110 nm polystyrene: V = π/6·110³ nm³ at 1.05 g/cm³ ≈ 440 MDa.
        assert!(
            (rb.mass_kda() / 1000.0 - 440.6).abs() < 1.0,
            "{}",
            rb.mass_kda()
        );
        // The paper: 950 kDa resolution for polystyrene ↔ 1.1 MDa for globular protein.
        let dsens = 950.0 / rb.mass_kda();
        let ps = mass_resolution_kda(dsens, rb.n, rb.density_g_cm3, &rb).unwrap();
        assert!((ps - 950.0).abs() < 1e-9);
        let prot = mass_resolution_kda(dsens, PROTEIN_N, PROTEIN_DENSITY_G_CM3, &rb).unwrap();
        assert!((prot / 1000.0 - 1.1).abs() < 0.06, "{prot}");
    }

    #[test]
    fn point_object_scaling() {
        let rb = RefBead::default();
        // A bead identical to the reference.
        let p = point_object(1.0, Some(0.01), 1.0, rb.n, rb.density_g_cm3, &rb).unwrap();
        assert!((p.sphere_d_nm - 110.0).abs() < 1e-9 && (p.mass_kda - rb.mass_kda()).abs() < 1e-6);
        // A 170 nm polystyrene bead: sensitivity (170/110)³.
        let s = (170.0f64 / 110.0).powi(3);
        let p = point_object(s, None, 1.0, rb.n, rb.density_g_cm3, &rb).unwrap();
        assert!((p.sphere_d_nm - 170.0).abs() < 1e-9);
        // Doubling the density doubles the mass.
        let p2 = point_object(s, None, 1.0, rb.n, 2.0 * rb.density_g_cm3, &rb).unwrap();
        assert!((p2.mass_kda / p.mass_kda - 2.0).abs() < 1e-12);
        let e = point_object(-1.0, None, 1.0, rb.n, 1.0, &rb)
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with("sens_obj = -1 is out of range: same sign as the contrast factor"),
            "{e}"
        );
        let e = point_object(1.0, None, 1.0, 1.333, 1.0, &rb)
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with("n_obj = 1.333 is out of range: n_obj ≠ n_medium"),
            "{e}"
        );
    }

    #[test]
    fn diameter_and_linear_density() {
        // A = d_bm/√(sens_bm·n_corr): a filament identical to the bead model gives d_bm.
        let c = DiameterCalib::from_sens_bm(10.0, 110.0, 1.57, 1.414, 1.333).unwrap();
        assert!((c.diameter_nm(10.0 * c.n_corr).unwrap() - 110.0).abs() < 1e-9);
        assert_eq!(c.diameter_nm(0.0).unwrap(), 0.0);
        for (bad, shown) in [(-0.1, "-0.1"), (f64::NAN, "NaN")] {
            let e = c.diameter_nm(bad).unwrap_err().to_string();
            assert!(
                e.starts_with(&format!(
                    "sens_corr = {shown} is out of range: sens_corr ≥ 0"
                )),
                "{e}"
            );
        }
        // With the paper's A = 58.6 nm the implied bead-model sensitivity is ≈ 10.
        let implied = (110.0f64 / 58.6).powi(2) / c.n_corr;
        assert!(implied > 9.0 && implied < 11.0, "{implied}");
        let l = LinDensCalib::from_sens_bm(10.0, 110.0, 1.572, 1.05, 1.572, 1.05, 1.333).unwrap();
        assert!((l.linear_density(10.0).unwrap() - l.mu_bm_mda_um).abs() < 1e-9);
        // 110 nm PS cylinder: 1.05 g/cm³·π/4·110² nm²·1000 nm per µm.
        // = 9503 nm² × 1000 nm × 632.3 Da/nm³ ≈ 6009 MDa/µm.
        assert!((l.mu_bm_mda_um - 6009.0).abs() < 3.0, "{}", l.mu_bm_mda_um);
        let (x, n) = protofilaments(13.0 * 13.75).unwrap();
        assert!((x - 13.0).abs() < 1e-12 && n == 13);
        assert!((PROTOFILAMENT_MDA_PER_UM - 13.75).abs() < 1e-12);
    }
}
