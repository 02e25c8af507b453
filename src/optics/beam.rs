//! The instrument's optics, validated and resolved once: [`ValidOptics`]
//! cannot exist invalid, and it carries the [`ResolvedBeam`], the angular-spectrum beam
//! (spectral waist, pupil apodisation) that `Optics::beam` selects. Every physics function
//! reads the beam from here; the mapping beam → (waist, apodisation) is written once, in
//! [`ResolvedBeam::of`]. Units as [`Optics`]: nm and mW in the fields; the resolved waist in µm.

use super::params::{Beam, Optics, OpticsError};
use serde::{Deserialize, Serialize};
use std::borrow::Cow;

/// The sphere whose response stands for a point dipole in the angular-spectrum beam (the vector
/// beam's Rayleigh tier, and the `mie` effect's small scatterers): 1 nm. Its scattering
/// amplitudes are taken in their dipole limit exactly (`MieTemplate::point_dipole`,
/// `Amplitudes::Dipole`); the size and index only set α, which the templates divide out.
pub const DIPOLE_D_NM: f64 = 1.0;
/// Index of the [`DIPOLE_D_NM`] sphere.
pub const DIPOLE_N: f64 = 1.5;

/// How the objective maps the pupil field onto the plane-wave spectrum.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
pub enum Apodization {
    /// Plane-wave amplitude per dk_x dk_y = f_w(θ) (no aplanatic factor; the Mie tier's beam
    /// until the one-beam work: its far field is ∝ cosθ f_w(θ)).
    #[default]
    None,
    /// Aplanatic (sine-condition) objective: far-field amplitude ∝ f_w(θ) √cosθ (energy
    /// conservation across the reference sphere, Richards & Wolf 1959, Proc. R. Soc. A 253,
    /// 358, eq. 2.22; Novotny & Hecht eq. 3.47), i.e. plane-wave amplitude per dk_x dk_y
    /// = f_w(θ)/√cosθ.
    Aplanatic,
}

impl Apodization {
    /// Factor g(cosθ) multiplying the Gaussian filling f_w in the amplitude per dk_x dk_y.
    #[inline]
    pub fn factor(self, cos_theta: f64) -> f64 {
        match self {
            Apodization::None => 1.0,
            Apodization::Aplanatic => 1.0 / cos_theta.max(1e-300).sqrt(),
        }
    }
}

/// The objective's aperture half-angle in the medium, asin(min(NA, n)/n), rad.
pub(super) fn theta_aperture(optics: &Optics) -> f64 {
    (optics.na.min(optics.n_medium) / optics.n_medium).asin()
}

/// Spectral waist (µm) of the Gaussian pupil filling with filling factor `f0` (Novotny & Hecht
/// eq. 3.52: f_w(θ) = exp(−sin²θ / (f0² sin²θ_max)), f0 = w_pupil / (f sinθ_max), the pupil's
/// 1/e field radius over the aperture radius). Since f_w = exp(−k² w_s² sin²θ / 4),
/// w_s = 2 / (k f0 sinθ_max). f0 = ∞ gives 0 (uniformly filled aperture). Errors for f0 ≤ 0.
pub fn filling_to_spectral_um(optics: &Optics, f0: f64) -> Result<f64, OpticsError> {
    if f0.is_nan() || f0 <= 0.0 {
        return Err(OpticsError::OutOfRange {
            name: "pupil_filling",
            value: f0,
            allowed: "pupil_filling > 0 (inf: uniformly filled aperture)".into(),
        });
    }
    if f0.is_infinite() {
        return Ok(0.0);
    }
    Ok(2.0 / (optics.k_per_um() * f0 * theta_aperture(optics).sin()))
}

/// How a beam renders point dipoles (and the finite-size rule's dipoles): decided once, with
/// the rest of the beam, in [`ResolvedBeam::of`]; every physics function that renders a dipole
/// matches on it instead of asking which beam it is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum DipoleTier {
    /// The paper's paraxial Rayleigh model (suppl. S2/S3): its template planes and closed-form
    /// response; only spheres the scene sends to the Mie tier go through the angular spectrum.
    ParaxialRayleigh,
    /// Every scatterer in the angular spectrum: a point dipole is a [`DIPOLE_D_NM`] sphere's
    /// dipole-limit Lorenz–Mie response per unit polarisability (always vectorial).
    AngularSpectrum,
}

/// The focused beam `Optics::beam` selects, as the angular spectrum every tier renders in
/// (docs/physics.md §9–10): the Gaussian spectrum's waist parameter and the pupil apodisation,
/// which beam it is, and how it renders point dipoles ([`DipoleTier`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ResolvedBeam {
    kind: Beam,
    spectral_waist_um: f64,
    apodization: Apodization,
    dipoles: DipoleTier,
}

impl ResolvedBeam {
    /// The one mapping beam → (spectral waist, apodisation, dipole tier):
    /// `Beam::Paraxial`: §9's beam, spectral waist w0, no aplanatic factor, point dipoles by
    /// the paper's Rayleigh model;
    /// `Beam::Vector`: the aplanatic focus (Richards & Wolf 1959) of Gaussian pupil filling
    /// `pupil_filling` ([`filling_to_spectral_um`]; ∞: uniformly filled, waist 0), every
    /// scatterer in the angular spectrum.
    fn of(optics: &Optics) -> Result<Self, OpticsError> {
        let (spectral_waist_um, apodization, dipoles) = match optics.beam {
            Beam::Paraxial => (
                optics.w0_um(),
                Apodization::None,
                DipoleTier::ParaxialRayleigh,
            ),
            Beam::Vector => (
                filling_to_spectral_um(optics, optics.pupil_filling)?,
                Apodization::Aplanatic,
                DipoleTier::AngularSpectrum,
            ),
        };
        Ok(Self {
            kind: optics.beam,
            spectral_waist_um,
            apodization,
            dipoles,
        })
    }

    /// Which beam (its name: `kind().name()`).
    pub fn kind(&self) -> Beam {
        self.kind
    }
    /// Spectral waist parameter of the angular spectrum, µm (0: uniformly filled aperture).
    pub fn spectral_waist_um(&self) -> f64 {
        self.spectral_waist_um
    }
    /// Pupil apodisation of the objective.
    pub fn apodization(&self) -> Apodization {
        self.apodization
    }
    /// How this beam renders point dipoles ([`DipoleTier`]).
    pub fn dipoles(&self) -> DipoleTier {
        self.dipoles
    }
}

/// Optics that passed [`Optics::validate`], with their beam resolved ([`ResolvedBeam`]).
/// Built only by [`ValidOptics::new`] (or `TryFrom<Optics>`, or deserialisation, which
/// validates); reads as [`Optics`] through `Deref`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "Optics", into = "Optics")]
pub struct ValidOptics {
    optics: Optics,
    beam: ResolvedBeam,
}

impl ValidOptics {
    /// Validate `optics` (the error names the field, its value and the allowed range) and
    /// resolve its beam.
    pub fn new(optics: Optics) -> Result<Self, OpticsError> {
        optics.validate()?;
        let beam = ResolvedBeam::of(&optics)?;
        Ok(Self { optics, beam })
    }

    /// The plain optics.
    pub fn optics(&self) -> &Optics {
        &self.optics
    }
    /// The plain optics, by value.
    pub fn into_optics(self) -> Optics {
        self.optics
    }
    /// The resolved beam.
    pub fn beam(&self) -> &ResolvedBeam {
        &self.beam
    }

    /// These optics with the detection quadrature raised to at least (`n_theta`, `n_phi`)
    /// nodes (never lowered), capped at the validated maximum 512: the beam does not depend
    /// on the quadrature, so it stays resolved.
    pub fn with_min_quadrature(&self, n_theta: usize, n_phi: usize) -> Self {
        let mut out = self.clone();
        out.optics.n_theta = self.optics.n_theta.max(n_theta.min(512));
        out.optics.n_phi = self.optics.n_phi.max(n_phi.min(512));
        out
    }
}

impl Default for ValidOptics {
    /// The paper's optics ([`Optics::default`]) in the uniformly filled vector beam.
    fn default() -> Self {
        Self {
            optics: Optics::default(),
            beam: ResolvedBeam {
                kind: Beam::Vector,
                spectral_waist_um: 0.0,
                apodization: Apodization::Aplanatic,
                dipoles: DipoleTier::AngularSpectrum,
            },
        }
    }
}

impl TryFrom<Optics> for ValidOptics {
    type Error = OpticsError;
    fn try_from(optics: Optics) -> Result<Self, OpticsError> {
        Self::new(optics)
    }
}

impl From<ValidOptics> for Optics {
    fn from(v: ValidOptics) -> Optics {
        v.optics
    }
}

impl std::ops::Deref for ValidOptics {
    type Target = Optics;
    fn deref(&self) -> &Optics {
        &self.optics
    }
}

/// What the physics functions accept as their optics: [`ValidOptics`] (used as they are: what
/// the session and the simulator pass) or plain [`Optics`] (validated and resolved here, once,
/// by [`ValidOptics::new`]: for studies and tests that build optics by hand).
pub trait OpticsArg {
    /// The validated optics.
    fn valid(&self) -> Result<Cow<'_, ValidOptics>, OpticsError>;
}

impl OpticsArg for ValidOptics {
    fn valid(&self) -> Result<Cow<'_, ValidOptics>, OpticsError> {
        Ok(Cow::Borrowed(self))
    }
}

impl OpticsArg for Optics {
    fn valid(&self) -> Result<Cow<'_, ValidOptics>, OpticsError> {
        ValidOptics::new(self.clone()).map(Cow::Owned)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The default is what validating the default optics gives; the paraxial beam's waist is
    /// w0 with no apodisation, the vector beam's is 2/(k f0 sinΘ) (f0 = 2: 0.5 / (k sinΘ)
    /// computed here by hand) with the aplanatic factor; invalid optics cannot be wrapped,
    /// and the error is validate's (field, value, range); JSON round-trips and refuses invalid
    /// optics.
    #[test]
    fn resolved_once_and_never_invalid() {
        assert_eq!(
            ValidOptics::new(Optics::default()).unwrap(),
            ValidOptics::default()
        );
        let p = ValidOptics::new(Optics {
            beam: Beam::Paraxial,
            w0_nm: 500.0,
            ..Optics::default()
        })
        .unwrap();
        assert_eq!(p.beam().spectral_waist_um(), 0.5);
        assert_eq!(p.beam().apodization(), Apodization::None);
        assert_eq!(p.beam().dipoles(), DipoleTier::ParaxialRayleigh);
        let v = ValidOptics::new(Optics {
            pupil_filling: 2.0,
            ..Optics::default()
        })
        .unwrap();
        // k = 2π·1.333/1.064 µm⁻¹, sinΘ = 1.2/1.333
        let k = 2.0 * std::f64::consts::PI * 1.333 / 1.064;
        let want = 2.0 / (k * 2.0 * (1.2 / 1.333));
        assert!((v.beam().spectral_waist_um() - want).abs() < 1e-15 * want);
        assert_eq!(v.beam().apodization(), Apodization::Aplanatic);
        assert_eq!(v.beam().dipoles(), DipoleTier::AngularSpectrum);
        let e = ValidOptics::new(Optics {
            na: 2.0,
            ..Optics::default()
        })
        .unwrap_err()
        .to_string();
        assert_eq!(e, "na = 2 is out of range: 0.01 ≤ na ≤ 1.7");
        let back: ValidOptics = serde_json::from_str(&serde_json::to_string(&v).unwrap()).unwrap();
        assert_eq!(back, v);
        let bad = serde_json::to_string(&Optics {
            n_medium: 0.5,
            ..Optics::default()
        })
        .unwrap();
        assert!(serde_json::from_str::<ValidOptics>(&bad)
            .unwrap_err()
            .to_string()
            .contains("n_medium = 0.5"));
        let q = v.with_min_quadrature(40, 1000);
        assert_eq!((q.n_theta, q.n_phi), (40, 512));
        assert_eq!(q.beam(), v.beam());
    }
}
