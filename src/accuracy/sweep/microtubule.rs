//! The microtubule family of the truth sweep (`microtubule.mu`): one microtubule-like filament
//! crossing an XY scan among point-like aggregates, cleaned and measured exactly as the
//! `aggregates::remove` then `microtubule::density` protocols do
//! ([`crate::analysis::microtubule`]: the same Rust functions their bindings call), at the
//! protocols' defaults (skip 1.2 µm, n 1.587, 1.35 g/cm³).
//!
//! Truth, by a path apart from the analysis: the scene's cylinder, μ = ρ·πd²/4 (ρ in g/cm³,
//! d in nm: 1 g/cm³ × 1 nm² × 1 µm = 10⁻¹⁸ g = 0.602 MDa; the bead model's calibration plays no
//! part). The answer is inside its domain when neither the removal nor the density has a
//! warning (a user reads both results).

use super::field::{clip_words, draw_clip, render_field};
use super::focus::Outcome;
use crate::analysis::microtubule::{density, remove_aggregates, AggregateOptions, Density};
use crate::analysis::orientation::{AngleCurve, AngleCurveOptions};
use crate::analysis::quantities::{LinDensCalib, PROTEIN_N};
use crate::analysis::template::Template;
use crate::instrument::sim::scene::{Bead, DiameterProfile, Filament, Scene, FILAMENT_SPACING_NM};
use crate::optics::params::Optics;
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use serde::Serialize;
use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};

/// Half the side of the microtubule scenes' field, µm.
const HALF_UM: f64 = 2.0;

/// The scenes' pixel sizes, nm (the orientation curve and the calibration are computed once
/// for each).
const PIXELS_NM: [u32; 4] = [20, 30, 40, 50];

/// The microtubule's density (g/cm³) and index: the protocol's defaults (protein, Sec. 6).
const DENSITY_G_CM3: f64 = 1.35;

/// The aggregates' index (the simulator's `add_aggregates` default: protein aggregates).
const AGGREGATE_N: f64 = 1.45;

/// MDa per µm of a cylinder of 1 nm² cross-section at 1 g/cm³ (Avogadro: 10⁻¹⁸ g × 6.022·10²³
/// Da/g = 0.602 MDa).
const MDA_PER_UM_PER_NM2_G_CM3: f64 = 0.602_214_076;

/// One microtubule scene: a straight filament `len_um` long and `d_nm` thick at `angle_deg`
/// from y, its midpoint at `centre` (µm); aggregates `[x µm, y µm, d nm]`; the paper's noise
/// × `noise`; pixels of `pixel_nm` on ±2 µm; the noise's `seed`; the digitiser's range.
#[derive(Debug, Clone, Serialize, serde::Deserialize, PartialEq)]
pub struct MicrotubuleCase {
    pub len_um: f64,
    pub d_nm: f64,
    pub angle_deg: f64,
    pub centre: [f64; 2],
    pub aggregates: Vec<[f64; 3]>,
    pub noise: f64,
    pub pixel_nm: u32,
    pub seed: u64,
    #[serde(default)]
    pub clip: Option<f64>,
}

impl MicrotubuleCase {
    /// A filament 6–15 µm long, 17–25 nm thick (13 protofilaments' mass as a solid protein
    /// cylinder is 16.7 nm; the simulator's filament is 25 nm), three in four within 10° of a
    /// QPD axis (the removal's domain: Sec. 6 fits the objects in the channel the filament does
    /// not show in, `MAX_FILAMENT_VISIBILITY`), one in four at any angle (its refusal), passing within
    /// 1 µm of the field's centre, its midpoint anywhere along the line so that an end may lie
    /// inside the field; 0–8 aggregates of 30–120 nm (log-uniform) on the line or within
    /// 0.4 µm of it, along the whole visible stretch (the uniform region and the ends); the
    /// paper's noise × 0–10 for half the scenes and × 0–4 for the others. The draw weights the
    /// domain (three in four near an axis, half the noise draws below 4×) so that N = 2000 gives
    /// ~200 answers inside it, where an even draw gave ~80 (a 2σ coverage then moves ±0.025
    /// between seeds by chance).
    pub(super) fn draw(rng: &mut ChaCha8Rng) -> MicrotubuleCase {
        let len_um = rng.random_range(6.0..15.0);
        let d_nm = rng.random_range(17.0..25.0);
        let angle_deg = if rng.random_range(0..4) == 0 {
            rng.random_range(-90.0f64..90.0)
        } else {
            let axis = if rng.random_range(0..2) == 0 {
                0.0
            } else {
                90.0
            };
            let a: f64 = axis + rng.random_range(-10.0..10.0);
            if a >= 90.0 {
                a - 180.0
            } else {
                a
            }
        };
        let a = angle_deg.to_radians();
        let (dir, normal) = ([a.sin(), a.cos()], [a.cos(), -a.sin()]);
        let off = rng.random_range(-1.0..1.0);
        let along = rng.random_range(-0.5..0.5) * (len_um - 1.0);
        let centre = [
            off * normal[0] + along * dir[0],
            off * normal[1] + along * dir[1],
        ];
        let n_agg = rng.random_range(0..=8);
        let aggregates = (0..n_agg)
            .map(|_| {
                let t = rng.random_range(-2.0 * HALF_UM..2.0 * HALF_UM);
                let p = if rng.random_range(0..2) == 0 {
                    0.0
                } else {
                    rng.random_range(-0.4..0.4)
                };
                let d = (30f64.ln() + rng.random::<f64>() * 4f64.ln()).exp();
                [
                    off * normal[0] + t * dir[0] + p * normal[0],
                    off * normal[1] + t * dir[1] + p * normal[1],
                    d,
                ]
            })
            .collect();
        // half the scenes over the whole range, half below 4× (where the filament is measured
        // at all: no answer above 5× was in the domain at N = 2000 over three seeds)
        let noise = if rng.random_range(0..2) == 0 {
            rng.random_range(0.0..10.0)
        } else {
            rng.random_range(0.0..4.0)
        };
        let pixel_nm = PIXELS_NM[rng.random_range(0..PIXELS_NM.len())];
        let seed = rng.random::<u64>();
        MicrotubuleCase {
            len_um,
            d_nm,
            angle_deg,
            centre,
            aggregates,
            noise,
            pixel_nm,
            seed,
            clip: draw_clip(rng),
        }
    }

    pub(super) fn describe(&self) -> String {
        format!(
            "microtubule {:.2} µm long, d {:.2} nm, at {:.1}°, centre ({:.2}, {:.2}) µm, aggregates {:?} (x, y µm, d nm), noise ×{:.4}, pixel {} nm on ±{HALF_UM} µm, seed {}{}",
            self.len_um,
            self.d_nm,
            self.angle_deg,
            self.centre[0],
            self.centre[1],
            self.aggregates
                .iter()
                .map(|a| (round3(a[0]), round3(a[1]), round3(a[2])))
                .collect::<Vec<_>>(),
            self.noise,
            self.pixel_nm,
            self.seed,
            clip_words(self.clip)
        )
    }

    /// The true linear density, MDa/µm: ρ·πd²/4.
    pub(super) fn truth_mu(&self) -> f64 {
        DENSITY_G_CM3 * std::f64::consts::PI / 4.0
            * self.d_nm
            * self.d_nm
            * MDA_PER_UM_PER_NM2_G_CM3
    }
}

fn round3(v: f64) -> f64 {
    (v * 1e3).round() / 1e3
}

/// The orientation curve and the linear-density calibration of one pixel size, as the
/// protocols compute them by default (`angle_curve(tpl, #{pixel_um})`, `lin_dens_calib(tpl,
/// #{pixel_um})`).
pub(super) struct MtCal {
    curve: AngleCurve,
    cal: LinDensCalib,
}

/// The calibrations by pixel size (nm), each computed once and shared by the scenes run in
/// parallel (None: it could not be computed).
#[derive(Default)]
pub(super) struct MtCals(Mutex<BTreeMap<u32, Option<Arc<MtCal>>>>);

impl MtCals {
    pub(super) fn get(&self, pixel_nm: u32, tpl: &Template) -> Option<Arc<MtCal>> {
        let mut m = self.0.lock().unwrap_or_else(|e| e.into_inner());
        m.entry(pixel_nm)
            .or_insert_with(|| {
                let opts = AngleCurveOptions {
                    pixel_um: pixel_nm as f64 / 1000.0,
                    ..AngleCurveOptions::default()
                };
                let curve = AngleCurve::compute(tpl, &opts).ok()?;
                let cal = LinDensCalib::from_template(
                    tpl,
                    PROTEIN_N,
                    DENSITY_G_CM3,
                    opts.pixel_um,
                    &crate::analysis::MeasureOptions::default(),
                    &crate::analysis::BeadModelOptions::default(),
                )
                .ok()?;
                Some(Arc::new(MtCal { curve, cal }))
            })
            .clone()
    }
}

/// What `--replay` prints of a microtubule scene.
pub(super) struct Answer {
    pub density: Density,
    /// Every warning of the removal and the density, once each.
    pub warnings: Vec<String>,
    /// The point objects the removal fitted and subtracted.
    pub n_objects: usize,
    /// The filament's visibility in the fitted channel (`Removal::visibility`).
    pub visibility: Option<f64>,
}

/// The scan of a microtubule scene: its filament and aggregates rendered on ±[`HALF_UM`] with
/// its noise and range (None: the simulator refused the scene).
fn case_scan(case: &MicrotubuleCase, optics: &Optics) -> Option<crate::data::Scan> {
    let a = case.angle_deg.to_radians();
    let dir = [a.sin(), a.cos()];
    let h = 0.5 * case.len_um;
    let c = case.centre;
    let mut sc = Scene::default();
    let filament = Filament {
        points: vec![
            [c[0] - h * dir[0], c[1] - h * dir[1]],
            [c[0] + h * dir[0], c[1] + h * dir[1]],
        ],
        z: 0.0,
        profile: DiameterProfile::Constant { d_nm: case.d_nm },
        n: PROTEIN_N,
        spacing_nm: FILAMENT_SPACING_NM,
    };
    if sc.add_filament(filament).is_err() {
        return None;
    }
    for &[x, y, d] in &case.aggregates {
        let bead = Bead {
            pos: [x, y, 0.0],
            d_nm: d,
            n: AGGREGATE_N,
        };
        if sc.add_bead(bead).is_err() {
            return None;
        }
    }
    let pixel = case.pixel_nm as f64 / 1000.0;
    render_field(
        optics,
        sc,
        HALF_UM,
        pixel,
        (case.noise, case.clip),
        case.seed,
    )
}

/// The microtubule family: one scene, its aggregates removed, its linear density against the
/// truth. Returns the outcome and the answer (for `--replay`): the density and every warning.
pub(super) fn microtubule_case(
    case: &MicrotubuleCase,
    tpl: &Template,
    optics: &Optics,
    cals: &MtCals,
) -> (Vec<(&'static str, Outcome)>, Option<Answer>) {
    let key = "microtubule.mu";
    let refused = || (vec![(key, Outcome::Refused)], None);
    let Some(cal) = cals.get(case.pixel_nm, tpl) else {
        return refused();
    };
    let Some(scan) = case_scan(case, optics) else {
        return refused();
    };
    let ao = AggregateOptions::default();
    let answer = remove_aggregates(&scan, tpl, &cal.curve, &ao).and_then(|r| {
        Ok((
            density(&r.cleaned.scan, &cal.curve, &cal.cal, ao.skip_um)?,
            r.warnings,
            r.cleaned.n_objects(),
            r.visibility,
            r.median_ratio,
        ))
    });
    let (d, removal_warnings, n_objects, visibility, median_ratio) = match answer {
        Ok(x) => x,
        Err(e) => return (vec![(key, Outcome::Flagged(vec![e]))], None),
    };
    let mut why = removal_warnings;
    for w in &d.warnings {
        if !why.contains(w) {
            why.push(w.clone());
        }
    }
    let truth = case.truth_mu();
    let o = if why.is_empty() {
        Outcome::Answer {
            value: d.mu_mda_um,
            truth,
            sigma: Some(d.mu_err_mda_um),
            // μ is a linear density, neither a count nor a diameter: an outlier beyond 4σ
            // (issue 41's rule). A 5 % limit, used until 2026-12-07, is 1.4–2.5σ where the
            // domain allows σ(μ) up to half a protofilament (6.9 MDa/µm, 2–3.5 % of μ), and
            // called 3 of 164 answers at 2.7–3.0σ outliers in the seed-2026 run
            rel_limit: None,
            what: format!(
                "μ {:.3} ± {:.3} MDa/µm vs truth {truth:.3} ({} maxima; {n_objects} objects removed, the median maximum × {}): {}",
                d.mu_mda_um,
                d.mu_err_mda_um,
                d.region.n_points,
                median_ratio.map_or("?".to_string(), |m| format!("{m:.4}")),
                case.describe()
            ),
        }
    } else {
        Outcome::Flagged(why.clone())
    };
    (
        vec![(key, o)],
        Some(Answer {
            density: d,
            warnings: why,
            n_objects,
            visibility,
        }),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Clausius–Mossotti factor (n² − n_m²)/(n² + 2n_m²): a Rayleigh particle's polarizability
    /// over its volume (the paper's Sec. 2 dipole).
    fn cm(n: f64, n_m: f64) -> f64 {
        (n * n - n_m * n_m) / (n * n + 2.0 * n_m * n_m)
    }

    /// A noise-free 20 nm microtubule 12 µm long, 3° from the QPD y axis (the weak channel),
    /// through the field's centre, no aggregates, at `pixel_nm`.
    fn bare_microtubule(pixel_nm: u32) -> MicrotubuleCase {
        MicrotubuleCase {
            len_um: 12.0,
            d_nm: 20.0,
            angle_deg: 3.0,
            centre: [0.0, 0.0],
            aggregates: vec![],
            noise: 0.0,
            pixel_nm,
            seed: 1,
            clip: None,
        }
    }

    /// What `density` says one object at the removal's detection limit would add to μ (its
    /// template injected on the filament, `undetected_rel`) against an independent path: a
    /// protein aggregate of that weight (by the Rayleigh volume and Clausius–Mossotti scaling
    /// from the reference bead) rendered by the simulator on the filament's axis at the middle
    /// of the uniform region, μ measured with it and without. Noise-free, so the detection
    /// limit is the removal's floor, `min_weight`.
    #[test]
    fn an_object_at_the_detection_limit_adds_to_mu_what_the_simulator_says() {
        let (optics, tpl) = super::super::sweep_optics().unwrap();
        let cals = MtCals::default();
        let bare = bare_microtubule(40);
        let cal = cals.get(bare.pixel_nm, &tpl).unwrap();
        let ao = AggregateOptions::default();
        let scan = case_scan(&bare, &optics).unwrap();
        let r = remove_aggregates(&scan, &tpl, &cal.curve, &ao).unwrap();
        assert_eq!(r.cleaned.n_objects(), 0);
        let limit = r.cleaned.detection_limit.unwrap();
        assert!(
            (limit - ao.min_weight).abs() < 1e-12 * ao.min_weight,
            "{limit}"
        );
        let d = density(&r.cleaned.scan, &cal.curve, &cal.cal, ao.skip_um).unwrap();
        let said = d.undetected_mda_um.unwrap();
        // the same weight as a protein aggregate of the simulator's, on the axis at the field's
        // centre (the middle of the uniform region: the filament crosses the whole field)
        let rb = tpl.reference;
        let k = ao.min_weight * cm(rb.n, rb.n_medium) / cm(AGGREGATE_N, rb.n_medium);
        let d_agg = rb.d_nm * k.cbrt();
        let with = MicrotubuleCase {
            aggregates: vec![[0.0, 0.0, d_agg]],
            ..bare.clone()
        };
        let mu = |c: &MicrotubuleCase| {
            let s = case_scan(c, &optics).unwrap();
            density(&s, &cal.curve, &cal.cal, ao.skip_um)
                .unwrap()
                .mu_mda_um
        };
        let rise = mu(&with) - mu(&bare);
        eprintln!("d_agg {d_agg:.2} nm: said {said:.4} MDa/µm, simulated {rise:.4}");
        assert!(
            (said - rise).abs() < 0.02 * rise,
            "said {said} MDa/µm, simulated {rise}"
        );
    }

    /// Detector noise does not bias μ where the rows' curvature is known to a few σ only: a
    /// 20 nm microtubule at 3° from the QPD y axis (the weak channel) at 20 nm pixels and 3×
    /// the paper's noise, 16 noise seeds, against the same scene without noise. Each line's
    /// vertex value (c0 − c1²/(4c2) with its second-order correction) read it 6.4 % low, with
    /// 2 of 16 answers within 2σ; the lines' parabolas read where their neighbours put the
    /// filament (`orientation::at_neighbours_vertex`) read it 0.4 % low, 15 of 16 within 2σ.
    #[test]
    fn detector_noise_does_not_bias_mu_in_the_weak_channel() {
        let (optics, tpl) = super::super::sweep_optics().unwrap();
        let cals = MtCals::default();
        let bare = bare_microtubule(20);
        let cal = cals.get(bare.pixel_nm, &tpl).unwrap();
        let skip = AggregateOptions::default().skip_um;
        let mu = |c: &MicrotubuleCase| {
            let s = case_scan(c, &optics).unwrap();
            let d = density(&s, &cal.curve, &cal.cal, skip).unwrap();
            (d.mu_mda_um, d.mu_err_mda_um)
        };
        let m0 = mu(&bare).0;
        let (rel, z): (Vec<f64>, Vec<f64>) = (0..16u64)
            .map(|k| {
                let (m, e) = mu(&MicrotubuleCase {
                    noise: 3.0,
                    seed: 1000 + k,
                    ..bare.clone()
                });
                (m / m0 - 1.0, (m - m0) / e)
            })
            .unzip();
        let mean = rel.iter().sum::<f64>() / rel.len() as f64;
        let within = z.iter().filter(|z| z.abs() < 2.0).count();
        eprintln!("mean {:.3} %, {within} of 16 within 2σ", 100.0 * mean);
        assert!(mean.abs() < 0.01, "μ biased by {:.2} %", 100.0 * mean);
        assert!(within >= 13, "{within} of 16 answers within 2σ");
    }
}
