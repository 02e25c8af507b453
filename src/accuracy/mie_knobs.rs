//! The Mie tier's own accuracy knob: the incident plane-wave grid of `optics::mie_beam`.
//! It lives here, not in optics, so that physics never depends on the report that measures it.

use super::{time_median, Knob, Point};
use crate::optics::mie::Complex64 as C64;
use crate::optics::mie_beam::{MieBeam, MieBeamSpec, DEFAULT_N_PHI_IN, DEFAULT_N_THETA_IN};
use crate::optics::params::REF_BEAD_N;
use crate::optics::ValidOptics;

/// Lateral radius (µm) of the region the `mie_grid` knob's error covers, and its test heights.
const KNOB_REGION_UM: f64 = 1.5;
const KNOB_HEIGHTS_UM: [f64; 3] = [0.0, 0.5, -1.0];

/// Accuracy knob (docs/accuracy.md): the incident plane-wave grid (n_theta_in, n_phi_in),
/// 500 nm polystyrene bead, default optics in the default (vector) beam
/// (`MieBeamSpec::of_beam`: the aplanatic focus; detection grid (16, 8), whose own error is the
/// `quadrature` knob). These are the grids of every direct Mie evaluation
/// (`MieBeamSpec::of_beam`: the scene's domain check, `max_sensitivity_in_beam`); the
/// simulator's Mie template planes size theirs by `MieBeamSpec::for_reach` instead. Error: the larger of (i) the relative error of (∂Sx/∂x)max (maximised
/// over z at x = y = 0) and (ii) the worst |ΔS| of (Sx, Sy, Sz) relative to the peak Sx over
/// 18 points within ρ ≤ 1.5 µm, |z| ≤ 1 µm (the default detection grid's reach), against a
/// (32, 16) reference. (i) alone converges to 1e-12 already at (8, 4): on the axis the
/// integrands are smooth; off the axis the phases k_j·x need the finer grid, hence (ii).
/// Time: one (Sx, Sy, Sz) evaluation at a point (median), the pair matrix already built.
pub fn knob_mie_grid(quick: bool) -> Knob {
    let o = ValidOptics::default();
    let n = C64::new(REF_BEAD_N, 0.0);
    let d = 500.0;
    let build = |nt: usize, np: usize| {
        MieBeam::new(
            &o,
            d,
            n,
            MieBeamSpec {
                n_theta_in: nt,
                n_phi_in: np,
                ..MieBeamSpec::of_beam(&o)
            },
        )
        .expect("valid default optics")
    };
    let (rt, rp) = (32, 16);
    let reference = build(rt, rp);
    let ref_max = reference.max_sensitivity_x().0;
    let peak = reference.response_unchecked(0.3, 0.0, 0.0)[0].abs();
    let pts: Vec<[f64; 3]> = (0..18)
        .map(|i| {
            let rho = KNOB_REGION_UM * ((i % 6) + 1) as f64 / 6.0;
            let a = 0.4 + 1.1 * i as f64;
            [rho * a.cos(), rho * a.sin(), KNOB_HEIGHTS_UM[i % 3]]
        })
        .collect();
    let ref_vals: Vec<[f64; 3]> = pts
        .iter()
        .map(|p| reference.response_unchecked(p[0], p[1], p[2]))
        .collect();
    let grids: &[(usize, usize)] = if quick {
        &[(6, 3), (8, 4), (12, 6), (16, 8)]
    } else {
        &[(4, 2), (6, 3), (8, 4), (10, 5), (12, 6), (16, 8), (24, 12)]
    };
    let points = grids
        .iter()
        .map(|&(nt, np)| {
            let m = build(nt, np);
            let mut err = ((m.max_sensitivity_x().0 - ref_max) / ref_max).abs();
            for (p, r) in pts.iter().zip(&ref_vals) {
                let v = m.response_unchecked(p[0], p[1], p[2]);
                for c in 0..3 {
                    err = err.max((v[c] - r[c]).abs() / peak);
                }
            }
            // A grid whose guaranteed reach is short of the region refuses part of it
            // (`response` errors beyond the reach): no answer there counts as a 100 % error.
            let reach = KNOB_HEIGHTS_UM
                .iter()
                .map(|&z| m.reach_um(z))
                .fold(f64::INFINITY, f64::min);
            let short = reach < KNOB_REGION_UM;
            if short {
                err = err.max(1.0);
            }
            let secs = time_median(if quick { 21 } else { 201 }, || {
                m.response_unchecked(0.31, -0.12, 0.05)
            });
            Point {
                setting: format!(
                    "n_theta_in = {nt}, n_phi_in = {np} ({} plane waves{})",
                    4 * nt * np,
                    if short {
                        format!("; reach {reach:.2} µm < {KNOB_REGION_UM} µm: refuses part of the region")
                    } else {
                        String::new()
                    }
                ),
                value: (4 * nt * np) as f64,
                error: err.max(1e-16),
                seconds: secs,
                is_default: nt == DEFAULT_N_THETA_IN && np == DEFAULT_N_PHI_IN,
            }
        })
        .collect();
    Knob {
        id: "mie_grid".into(),
        title: "Mie tier: incident plane-wave grid, 500 nm bead, vector beam".into(),
        metric: "max of rel. error of (∂Sx/∂x)max and worst |ΔS|/peak within ρ ≤ 1.5 µm".into(),
        timed: "one (Sx, Sy, Sz) evaluation at a point (512 detection nodes)".into(),
        reference: format!("n_theta_in = {rt}, n_phi_in = {rp}"),
        points,
    }
}
