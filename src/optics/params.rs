//! Optical parameters of the set-up, with the paper's defaults, and their validation.

use serde::{Deserialize, Serialize};

/// Errors from physics functions: always name the argument, its value and the allowed range.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum OpticsError {
    #[error("{name} = {value} is out of range: {allowed}")]
    OutOfRange {
        name: &'static str,
        value: f64,
        allowed: String,
    },
    #[error("{0}")]
    Invalid(String),
}

/// Check `lo <= value <= hi` and finiteness.
pub fn check_range(name: &'static str, value: f64, lo: f64, hi: f64) -> Result<f64, OpticsError> {
    checked(name, value, value >= lo && value <= hi, || {
        format!("{lo} ≤ {name} ≤ {hi}")
    })
}

/// Check `value > lo` (exclusive) and finiteness.
pub fn check_above(name: &'static str, value: f64, lo: f64) -> Result<f64, OpticsError> {
    checked(name, value, value > lo, || {
        format!("{name} > {lo} (finite)")
    })
}

/// `value` if it is finite and `ok`, else the out-of-range error stating what is `allowed`.
fn checked(
    name: &'static str,
    value: f64,
    ok: bool,
    allowed: impl FnOnce() -> String,
) -> Result<f64, OpticsError> {
    if value.is_finite() && ok {
        Ok(value)
    } else {
        Err(OpticsError::OutOfRange {
            name,
            value,
            allowed: allowed(),
        })
    }
}

/// The optics of the instrument. Units as at the script boundary: nm, mW.
///
/// Defaults are the paper's (main text Sec. 2, 3.1 and suppl. S2/S3): λ = 1064 nm, water
/// n = 1.333, w0 = 400 nm (1/e² intensity radius), 0.13 mW at the focus. The detection cone is
/// the smaller of the condenser NA and the QPD size (`qpd_na`, the NA that the QPD's radius
/// subtends); the paper's objective is a 1.2 NA water lens, which we take as the default
/// detection NA.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct Optics {
    pub wavelength_nm: f64,
    pub n_medium: f64,
    pub w0_nm: f64,
    /// Condenser numerical aperture (in the immersion of the condenser; limited to n_medium by
    /// the aqueous sample).
    pub na: f64,
    /// NA subtended by the QPD active area (f64::INFINITY: the QPD is not limiting).
    #[serde(deserialize_with = "null_is_inf")]
    pub qpd_na: f64,
    pub power_mw: f64,
    /// Quadrature nodes over θ in the detection cone (accuracy knob).
    pub n_theta: usize,
    /// Quadrature nodes over φ per quadrant (accuracy knob).
    pub n_phi: usize,
    /// Which focused beam every tier is rendered in ([`Beam`]).
    pub beam: Beam,
    /// Gaussian pupil filling factor f0 of the objective for `Beam::Vector` (Novotny & Hecht
    /// eq. 3.52): f_w(θ) = exp(−sin²θ / (f0² sin²θ_max)), f0 = pupil 1/e field radius over the
    /// aperture radius; f64::INFINITY = uniformly filled (the real instrument). Unused by
    /// `Beam::Paraxial`, whose width is `w0_nm`.
    #[serde(deserialize_with = "null_is_inf")]
    pub pupil_filling: f64,
}

/// JSON has no infinity: serde_json writes f64::INFINITY as `null`; read `null` back as
/// infinity (`qpd_na`, `pupil_filling`: "not limiting" / "uniformly filled").
fn null_is_inf<'de, D: serde::Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
    Ok(Option::<f64>::deserialize(d)?.unwrap_or(f64::INFINITY))
}

/// The focused beam of the instrument.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Beam {
    /// The paper's paraxial scalar Gaussian of waist w0 (suppl. S2/S3), a named approximation:
    /// the paper's numbers are reproduced through it.
    Paraxial,
    /// Vectorial focus of an aplanatic objective of NA `na` (Richards & Wolf 1959, Proc. R. Soc.
    /// A 253, 358; Novotny & Hecht §3.6): angular spectrum with the 1/√cosθ apodisation, Gaussian
    /// pupil filling `pupil_filling`, x-polarised; every scatterer (point dipoles, finite-size
    /// spheres, filaments, aggregates, Lorenz–Mie spheres) is rendered in it
    /// (`optics::mie_beam`, docs/physics.md §10). The default: the real instrument.
    #[default]
    Vector,
}

impl Beam {
    /// The name used by `set_optics(#{beam: …})`.
    pub fn name(self) -> &'static str {
        match self {
            Beam::Paraxial => "paraxial",
            Beam::Vector => "vector",
        }
    }
    /// Parse a script name; the error names the key, the value and the allowed names.
    pub fn parse(s: &str) -> Result<Self, OpticsError> {
        match s {
            "paraxial" => Ok(Beam::Paraxial),
            "vector" => Ok(Beam::Vector),
            _ => Err(OpticsError::Invalid(format!(
                "beam = \"{s}\" is not a beam model: allowed \"vector\" (aplanatic vectorial focus) or \"paraxial\" (the paper's scalar Gaussian, suppl. S3)"
            ))),
        }
    }
}

/// Reference bead of the paper: 110 nm polystyrene, n = 1.572 at 1064 nm, 1.05 g/cm³.
pub const REF_BEAD_D_NM: f64 = 110.0;
pub const REF_BEAD_N: f64 = 1.572;
pub const REF_BEAD_DENSITY_G_CM3: f64 = 1.05;

impl Default for Optics {
    fn default() -> Self {
        Self {
            wavelength_nm: 1064.0,
            n_medium: 1.333,
            w0_nm: 400.0,
            na: 1.2,
            qpd_na: f64::INFINITY,
            power_mw: 0.13,
            // The knee of the accuracy report (docs/accuracy.md): Gauss–Legendre converges
            // exponentially; (16, 8) is within 3.2e-6 of the peak Sx of the (128, 64) reference.
            n_theta: 16,
            n_phi: 8,
            beam: Beam::Vector,
            pupil_filling: f64::INFINITY,
        }
    }
}

impl Optics {
    /// Validate every field; the message names the field, its value and the allowed range.
    pub fn validate(&self) -> Result<(), OpticsError> {
        check_range("wavelength_nm", self.wavelength_nm, 100.0, 20000.0)?;
        check_range("n_medium", self.n_medium, 1.0, 3.0)?;
        check_range("w0_nm", self.w0_nm, 50.0, 100000.0)?;
        check_range("na", self.na, 0.01, 1.7)?;
        if self.qpd_na.is_nan() || self.qpd_na <= 0.0 {
            return Err(OpticsError::OutOfRange {
                name: "qpd_na",
                value: self.qpd_na,
                allowed: "qpd_na > 0 (inf: QPD not limiting)".into(),
            });
        }
        check_range("power_mw", self.power_mw, 0.0, 10000.0)?;
        check_range("n_theta", self.n_theta as f64, 4.0, 512.0)?;
        check_range("n_phi", self.n_phi as f64, 2.0, 512.0)?;
        if self.pupil_filling.is_nan() || self.pupil_filling <= 0.0 {
            return Err(OpticsError::OutOfRange {
                name: "pupil_filling",
                value: self.pupil_filling,
                allowed: "pupil_filling > 0 (inf: uniformly filled aperture)".into(),
            });
        }
        // The beam must fit in the paraxial picture at least loosely: k·w0 > 1.
        if self.k_per_um() * self.w0_um() <= 1.0 {
            return Err(OpticsError::Invalid(format!(
                "w0_nm = {} is below λ/(2π n) = {:.0} nm: the Gaussian-beam model does not apply",
                self.w0_nm,
                self.wavelength_nm / (2.0 * std::f64::consts::PI * self.n_medium)
            )));
        }
        Ok(())
    }

    /// Wavenumber in the medium, k = 2π n / λ0, in µm⁻¹.
    pub fn k_per_um(&self) -> f64 {
        2.0 * std::f64::consts::PI * self.n_medium / (self.wavelength_nm * 1e-3)
    }
    /// Beam waist in µm.
    pub fn w0_um(&self) -> f64 {
        self.w0_nm * 1e-3
    }
    /// Rayleigh range z_R = π w0² n / λ0 (suppl. S2), µm.
    pub fn z_r_um(&self) -> f64 {
        std::f64::consts::PI * self.w0_um().powi(2) * self.n_medium / (self.wavelength_nm * 1e-3)
    }
    /// Half-angle of the detection cone in the medium, Θ = asin(min(NA, NA_qpd, n)/n).
    pub fn theta_max(&self) -> f64 {
        (self.na.min(self.qpd_na).min(self.n_medium) / self.n_medium).asin()
    }
}

#[cfg(test)]
mod beam_tests {
    use super::*;

    /// The beam key parses the two names and refuses others naming the key and the choices;
    /// a non-positive pupil filling is refused; the optics round-trip through JSON (scan
    /// metadata) with the new keys.
    #[test]
    fn beam_names_pupil_filling_and_json_round_trip() {
        assert_eq!(Beam::parse("vector").unwrap(), Beam::Vector);
        assert_eq!(Beam::parse("paraxial").unwrap(), Beam::Paraxial);
        let e = Beam::parse("gauss").unwrap_err().to_string();
        assert!(
            e.contains("beam = \"gauss\"") && e.contains("\"vector\""),
            "{e}"
        );
        let bad = Optics {
            pupil_filling: 0.0,
            ..Optics::default()
        };
        assert!(bad
            .validate()
            .unwrap_err()
            .to_string()
            .contains("pupil_filling = 0"));
        let o = Optics {
            beam: Beam::Vector,
            pupil_filling: 1.5,
            ..Optics::default()
        };
        let back: Optics = serde_json::from_str(&serde_json::to_string(&o).unwrap()).unwrap();
        assert_eq!(back, o);
        let d: Optics = serde_json::from_str(&serde_json::to_string(&Optics::default()).unwrap())
            .unwrap_or_else(|e| panic!("default optics JSON: {e}"));
        assert_eq!(d.beam, Beam::Vector);
        assert!(d.pupil_filling.is_infinite());
    }
}
