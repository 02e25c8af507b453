//! Instrument-time trade-off: mass and linear-density uncertainty against the
//! total scan time on the simulated instrument (virtual clock) with the `detector_noise` effect
//! at the project's paper-noise level (docs/physics.md §7).
//!
//! Every scan goes through the real scan engine (`acquire::run_plan`) on the simulated stage and
//! QPD, so the times are what the virtual clock counts: dwell × pixels, plus the simulated stage
//! moves (2 ms each, `SimConfig::move_time_s`) which the report states separately.
//!
//! **Scaling law.** With white noise of σ_s per sample at rate f, a pixel read for a dwell t has
//! σ_pix = σ_s/√(f t). A one-bead least-squares fit of the weight C (positions are orthogonal to
//! the weight at the bead centre by symmetry) has σ_C = σ_pix/√(Σ_pixels (Tx² + Ty²)), and the sum
//! is (1/h²)∫(Tx² + Ty²) dA = I/h² for pixel pitch h. Hence
//! σ_C = σ_s · h / √(f t I) = σ_s / √(f · (t/h²) · I):
//! the mass uncertainty depends only on the time spent per unit area, t/h² (s/µm²), not on the
//! pixel size or dwell separately, as long as the scan covers the template's support.

use super::analysis_knobs::PIXEL_UM;
use super::{Knob, Point};
use crate::acquire::{run_plan, Axis, Plan, ScanEnv, SoftLimits, Sweep};
use crate::analysis::bead_model::BeadModelOptions;
use crate::analysis::crlb::{beads_crlb, pixel_sigma};
use crate::analysis::filament_fit::{
    fit_line_filament, lambda_of_diameter, line_crlb, volume_per_um, LineFilament, LineFitOptions,
};
use crate::analysis::fit::{fit_beads, BeadInit, Channels, FitOptions};
use crate::analysis::orientation::{
    measure_filament, AngleCurve, AngleCurveOptions, MeasureOptions,
};
use crate::analysis::quantities::{
    self, mass_resolution_kda, LinDensCalib, PROTEIN_DENSITY_G_CM3, PROTEIN_N,
};
use crate::analysis::scaling::mass_kda;
use crate::analysis::template::{RefBead, Template};
use crate::data::Scan;
use crate::instrument::sim::scene::{
    Bead, DetectorNoise, DiameterProfile, Filament, Scene, PAPER_DETECTOR_SIGMA_SAMPLE,
};
use crate::instrument::sim::{SimConfig, SimCore};
use crate::instrument::Clock;
use crate::optics::params::{Optics, REF_BEAD_N};
use crate::optics::rayleigh::DetectorModel;
use serde::Serialize;
use std::sync::atomic::AtomicBool;

/// The paper's mass resolution for polystyrene (Sec. 3.2), kDa.
pub const PAPER_RESOLUTION_PS_KDA: f64 = 950.0;
/// The paper's mass resolution for globular protein (Sec. 3.2), kDa.
pub const PAPER_RESOLUTION_PROTEIN_KDA: f64 = 1100.0;
/// Pixels per side of the trade-off scans.
pub const SCAN_PIXELS: usize = 64;

/// One XY scan of `scene` through the scan engine on the simulated instrument: 64×64 pixels of
/// 50 nm from (0, 0), dwell `dwell_s`. Returns the scan and the virtual-clock time it took.
pub fn engine_scan(optics: &Optics, scene: &Scene, dwell_s: f64) -> Result<(Scan, f64), String> {
    let core = SimCore::new(optics, scene, SimConfig::default()).map_err(|e| e.to_string())?;
    let mut inst = core.instrument(0.0);
    let n = SCAN_PIXELS;
    let to = (n - 1) as f64 * PIXEL_UM;
    let sweep = |a| Sweep::new("accuracy", a, 0.0, to, n as i64, "n").map_err(|e| e.0);
    let plan = Plan::grid(
        "accuracy",
        sweep(Axis::X)?,
        sweep(Axis::Y)?,
        vec![(Axis::Z, 0.0)],
        dwell_s,
        false,
        false,
    )
    .map_err(|e| e.0)?;
    let limits = SoftLimits::default();
    let abort = AtomicBool::new(false);
    let log = |_: &str| {};
    let save = |_: &Scan| Ok(std::path::PathBuf::from("(not saved)"));
    let env = ScanEnv {
        meta: serde_json::json!({"script": {"path": "bfpscope accuracy"}}),
        ..ScanEnv::plain(&limits, &abort, &log, &save)
    };
    let t0 = core.clock.now();
    let run = run_plan(&mut inst, &plan, &env).map_err(|e| e.to_string())?;
    let dt = core.clock.now() - t0;
    run.summary()?;
    Ok((run.scan, dt))
}

/// One row of a trade-off sweep.
#[derive(Debug, Clone, Serialize)]
pub struct TradeRow {
    pub dwell_s: f64,
    /// dwell × pixels, s.
    pub scan_s: f64,
    /// Virtual-clock time of the whole scan (moves included), s.
    pub clock_s: f64,
    /// Mean of the fits' own 1σ over the seeds (kDa for beads, MDa/µm for the microtubule).
    pub sigma_fit: f64,
    /// Standard deviation of the estimates over the seeds (same unit).
    pub sigma_scatter: f64,
    /// Mean estimate (kDa or MDa/µm).
    pub mean: f64,
    /// Protein-equivalent of `sigma_fit` (beads only), kDa.
    pub sigma_protein_kda: f64,
    /// Fit with Sx only (the paper's "fit to the S_x response"), mean 1σ, kDa (beads only).
    pub sigma_fit_sx_only: f64,
    /// Seeds in which the object was found and measured.
    pub found: usize,
    /// Cramér–Rao bound of the row's quantity (same unit as `sigma_fit`) for this plan and
    /// scene at the truth: the Fisher information of the scan's Sx and Sy pixels
    /// (`analysis::crlb`) with the simulator's pixel noise σ_s/√(dwell·rate).
    pub crlb: f64,
    /// Every estimator of the row: σ observed over the seeds against its bound.
    pub estimators: Vec<Efficiency>,
}

/// One estimator at one dwell: the scatter of its estimates over the noise seeds against the
/// Cramér–Rao bound of the same plan and scene (`efficiency` = scatter ÷ CRLB: 1 is the
/// information limit; an estimator that reaches it cannot be beaten by any unbiased one).
#[derive(Debug, Clone, Serialize)]
pub struct Efficiency {
    /// What is estimated ("bead x", "filament angle", …).
    pub estimator: &'static str,
    /// Unit of `mean`, `scatter`, `fit_sigma` and `crlb`.
    pub unit: &'static str,
    pub mean: f64,
    /// Sample standard deviation of the estimates over the seeds where the object was found.
    pub scatter: f64,
    /// Mean of the estimator's own 1σ (NaN when it states none).
    pub fit_sigma: f64,
    pub crlb: f64,
    /// Seeds with an estimate.
    pub n: usize,
}

impl Efficiency {
    /// From the estimates `values` (NaN where there is none), the estimator's own 1σ `errors`
    /// and the bound `crlb`.
    fn of(
        estimator: &'static str,
        unit: &'static str,
        values: &[f64],
        errors: &[f64],
        crlb: f64,
    ) -> Self {
        let (mean, scatter) = mean_std(values);
        Self {
            estimator,
            unit,
            mean,
            scatter,
            fit_sigma: mean_std(errors).0,
            crlb,
            n: values.iter().filter(|v| v.is_finite()).count(),
        }
    }

    /// σ observed over the seeds ÷ CRLB.
    pub fn efficiency(&self) -> f64 {
        self.scatter / self.crlb
    }
}

impl TradeRow {
    /// σ observed over the seeds ÷ CRLB of the row's quantity.
    pub fn efficiency(&self) -> f64 {
        self.sigma_scatter / self.crlb
    }

    /// The row of one dwell (s) over the seeds: the estimates `values` (NaN where the object was
    /// not found) and the fits' own 1σ `errors`; a scan of `npix` pixels that took `clock_s`
    /// on the virtual clock. The beads-only columns are NaN.
    fn measured(dwell_s: f64, npix: f64, clock_s: f64, values: &[f64], errors: &[f64]) -> Self {
        let (mean, sigma_scatter) = mean_std(values);
        Self {
            dwell_s,
            scan_s: dwell_s * npix,
            clock_s,
            sigma_fit: mean_std(errors).0,
            sigma_scatter,
            mean,
            sigma_protein_kda: f64::NAN,
            sigma_fit_sx_only: f64::NAN,
            found: values.iter().filter(|v| v.is_finite()).count(),
            crlb: f64::NAN,
            estimators: vec![],
        }
    }
}

/// The bead and microtubule trade-offs and the calibration numbers derived from them.
#[derive(Debug, Clone, Serialize)]
pub struct Tradeoff {
    pub bead: Vec<TradeRow>,
    /// The microtubule by the paper's per-row maxima (Sec. 5).
    pub microtubule: Vec<TradeRow>,
    /// The same scans by the whole-image bead-model fit (`analysis::filament_fit`).
    pub microtubule_fit: Vec<TradeRow>,
    /// Number of noise seeds per point.
    pub seeds: usize,
    /// 1σ mass (kDa, polystyrene) × √(scan time s) from a fit over the bead rows (the 1/√t law).
    pub bead_k_kda_sqrt_s: f64,
    /// Same with the Sx-only fit.
    pub bead_k_sx_only: f64,
    /// Protein-equivalent constant.
    pub bead_k_protein: f64,
    /// σ_μ (MDa/µm) × √(scan time s) for the microtubule (from the dwells where every seed
    /// found the filament).
    pub mt_k: f64,
    /// The same constant for the whole-image fit (its own 1σ, every dwell where it found the
    /// filament in every seed).
    pub mt_fit_k: f64,
    /// The Cramér–Rao bounds × √(scan time): the bead's mass (kDa·√s) and the microtubule's
    /// linear density (MDa/µm·√s) of the 64×64 raster (exact: the bound scales as 1/√dwell).
    pub bead_crlb_k: f64,
    pub mt_crlb_k: f64,
    /// True linear density of the simulated 13-protofilament microtubule, MDa/µm.
    pub mt_true_mu: f64,
    /// Template integral I = ∫(Tx² + Ty²) dA of the reference bead (δP/P units² µm²).
    pub template_integral: f64,
    /// Mass of the reference bead, kDa.
    pub ref_mass_kda: f64,
    /// Averaging: `averaged_scans` scans of `averaged.dwell_s` averaged pixel by pixel (its
    /// `scan_s` and `clock_s` are the totals over the scans).
    pub averaged: TradeRow,
    pub averaged_scans: usize,
}

impl Tradeoff {
    /// Scan time (dwell × pixels, s) at which the bead's 1σ mass reaches `target_kda` for the
    /// given constant (σ = k/√t).
    pub fn time_for(k: f64, target: f64) -> f64 {
        (k / target).powi(2)
    }

    /// The scaling law's 1σ mass (kDa, polystyrene) for a one-bead fit of both channels at
    /// `dwell_s` per pixel of `pixel_um`: σ_s·h·m_rb/√(f·t·I) (module docs).
    pub fn predicted_sigma_kda(&self, dwell_s: f64, pixel_um: f64) -> f64 {
        let f = SimConfig::default().sample_rate;
        PAPER_DETECTOR_SIGMA_SAMPLE * pixel_um / (f * dwell_s * self.template_integral).sqrt()
            * self.ref_mass_kda
    }

    /// Shortest scan time (s) at which the microtubule was found in every seed.
    pub fn mt_min_found_s(&self) -> Option<f64> {
        self.microtubule
            .iter()
            .filter(|r| r.found == self.seeds)
            .map(|r| r.scan_s)
            .reduce(f64::min)
    }
}

/// Least-squares k in σ = k/√t (fit of log σ = log k − ½ log t with the slope fixed).
fn sqrt_law(rows: &[TradeRow], f: impl Fn(&TradeRow) -> f64) -> f64 {
    let v: Vec<f64> = rows
        .iter()
        .map(|r| (f(r) * r.scan_s.sqrt()).ln())
        .filter(|v| v.is_finite())
        .collect();
    (v.iter().sum::<f64>() / v.len().max(1) as f64).exp()
}

/// Mean and sample standard deviation of the finite values (NaN when there are none).
fn mean_std(v: &[f64]) -> (f64, f64) {
    let v: Vec<f64> = v.iter().copied().filter(|x| x.is_finite()).collect();
    let n = v.len() as f64;
    let m = v.iter().sum::<f64>() / n;
    let s = if v.len() > 1 {
        (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (n - 1.0)).sqrt()
    } else {
        f64::NAN
    };
    (m, s)
}

/// ∫(Tx² + Ty²) dA of a template in the data's units (T/norm_factor, δP/P), (δP/P)²·µm².
pub fn template_integral(tpl: &Template, h: f64) -> f64 {
    let ((u0, u1), (v0, v1)) = tpl.extent();
    let (nu, nv) = (((u1 - u0) / h) as i64, ((v1 - v0) / h) as i64);
    let mut s = 0.0;
    for j in 0..=nv {
        for i in 0..=nu {
            let t = tpl.eval(u0 + i as f64 * h, v0 + j as f64 * h);
            s += t[0] * t[0] + t[1] * t[1];
        }
    }
    s * h * h / (tpl.norm_factor * tpl.norm_factor)
}

/// Equivalent diameter (nm) of a protein cylinder with the linear density of an
/// `npf`-protofilament microtubule (110 kDa per 8 nm per protofilament, ρ = 1/0.745 g/cm³).
pub fn mt_equivalent_d_nm(npf: u32) -> f64 {
    let mu = npf as f64 * quantities::PROTOFILAMENT_MDA_PER_UM;
    let da_per_nm3 = PROTEIN_DENSITY_G_CM3 * 1e-21 * quantities::DA_PER_G;
    let area_nm2 = mu * 1e6 / 1000.0 / da_per_nm3;
    (4.0 * area_nm2 / std::f64::consts::PI).sqrt()
}

/// One polystyrene bead of diameter `d_nm` at (x, y) µm, z = 0, with `detector_noise` at the
/// project's paper-noise level and the given seed.
fn noisy_bead_scene(xy: [f64; 2], d_nm: f64, seed: u64) -> Result<Scene, String> {
    let mut sc = Scene::default();
    sc.add_bead(Bead {
        pos: [xy[0], xy[1], 0.0],
        d_nm,
        n: REF_BEAD_N,
    })
    .map_err(|e| e.to_string())?;
    sc.effects.detector_noise = Some(DetectorNoise {
        sigma_sample: PAPER_DETECTOR_SIGMA_SAMPLE,
    });
    sc.seed = seed;
    Ok(sc)
}

/// Columns (= rows) of the trade-off scans, µm: 64 pixels of 50 nm from 0.
fn scan_axis() -> Vec<f64> {
    (0..SCAN_PIXELS).map(|i| i as f64 * PIXEL_UM).collect()
}

/// Per-pixel noise of a trade-off scan at `dwell_s` (the simulator's paper-level detector
/// noise averaged over the dwell's samples).
fn trade_pixel_sigma(dwell_s: f64) -> Result<f64, String> {
    pixel_sigma(
        PAPER_DETECTOR_SIGMA_SAMPLE,
        dwell_s,
        SimConfig::default().sample_rate,
    )
    .map_err(|e| e.to_string())
}

/// Where the trade-off's bead is (µm): off the pixel grid in y, so the fit is not helped by
/// a symmetric sampling.
fn bead_truth(c: f64) -> [f64; 2] {
    [c, c + 0.013]
}

/// The bead's rows of the trade-off: per dwell, `seeds` noisy scans of the bead centred near
/// `c`, fitted with both channels and Sx only; beside them the Cramér–Rao bounds of x, y and
/// the weight (mass) of the same plan and scene (`analysis::crlb::beads_crlb` at the truth).
fn bead_rows(
    optics: &Optics,
    tpl: &Template,
    rb: RefBead,
    dwells: &[f64],
    seeds: usize,
    c: f64,
) -> Result<Vec<TradeRow>, String> {
    let es = |e: crate::analysis::AnalysisError| e.to_string();
    let npix = (SCAN_PIXELS * SCAN_PIXELS) as f64;
    let axis = scan_axis();
    let truth = bead_truth(c);
    let mut bead = vec![];
    for (i, &dwell) in dwells.iter().enumerate() {
        let (mut m, mut e, mut e_sx, mut e_p, mut clock) = (vec![], vec![], vec![], vec![], 0.0);
        let (mut xs, mut ys, mut xe, mut ye) = (vec![], vec![], vec![], vec![]);
        for s in 0..seeds {
            let sc = noisy_bead_scene(truth, rb.d_nm, 10_000 + 100 * i as u64 + s as u64)?;
            let (scan, dt) = engine_scan(optics, &sc, dwell)?;
            clock += dt / seeds as f64;
            let init = Some(vec![BeadInit {
                x: c,
                y: c,
                weight: 1.0,
            }]);
            for (ch, out) in [(Channels::Both, &mut e), (Channels::Sx, &mut e_sx)] {
                let r = fit_beads(
                    &scan.sx,
                    &scan.sy,
                    tpl,
                    &FitOptions {
                        channels: ch,
                        init: init.clone(),
                        ..FitOptions::default()
                    },
                )
                .map_err(es)?;
                let b = r.beads[0];
                let we = b.weight_err.ok_or("bead fit without an uncertainty")?;
                out.push(mass_resolution_kda(we, rb.n, rb.density_g_cm3, &rb).map_err(es)?);
                if ch == Channels::Both {
                    m.push(b.weight * rb.mass_kda());
                    e_p.push(
                        mass_resolution_kda(we, PROTEIN_N, PROTEIN_DENSITY_G_CM3, &rb)
                            .map_err(es)?,
                    );
                    xs.push(b.x * 1e3);
                    ys.push(b.y * 1e3);
                    xe.push(b.x_err.unwrap_or(f64::NAN) * 1e3);
                    ye.push(b.y_err.unwrap_or(f64::NAN) * 1e3);
                }
            }
        }
        // the bound of this plan (64×64 × 50 nm, Sx and Sy, the dwell's pixel noise) at the
        // simulated bead (weight 1: it is the reference bead)
        let sigma = trade_pixel_sigma(dwell)?;
        let sig = |_: usize, _: usize, _: usize| Some(sigma);
        let bd = beads_crlb(
            tpl,
            &[BeadInit {
                x: truth[0],
                y: truth[1],
                weight: 1.0,
            }],
            &axis,
            &axis,
            &[0, 1],
            &sig,
        )
        .map_err(es)?[0];
        let mass_crlb = mass_resolution_kda(bd.weight, rb.n, rb.density_g_cm3, &rb).map_err(es)?;
        bead.push(TradeRow {
            sigma_protein_kda: mean_std(&e_p).0,
            sigma_fit_sx_only: mean_std(&e_sx).0,
            crlb: mass_crlb,
            estimators: vec![
                Efficiency::of("bead x", "nm", &xs, &xe, bd.x * 1e3),
                Efficiency::of("bead y", "nm", &ys, &ye, bd.y * 1e3),
                Efficiency::of("bead mass (weight)", "kDa", &m, &e, mass_crlb),
            ],
            ..TradeRow::measured(dwell, npix, clock, &m, &e)
        });
    }

    Ok(bead)
}

/// Averaging: `k_avg` scans of dwell `d_avg` averaged, fitted as one (against one scan of
/// dwell k·d in the bead rows).
fn averaged_row(
    optics: &Optics,
    tpl: &Template,
    rb: RefBead,
    k_avg: usize,
    d_avg: f64,
    seeds: usize,
    c: f64,
) -> Result<TradeRow, String> {
    let es = |e: crate::analysis::AnalysisError| e.to_string();
    let npix = (SCAN_PIXELS * SCAN_PIXELS) as f64;
    let (mut m, mut e, mut clock) = (vec![], vec![], 0.0);
    for s in 0..seeds {
        let mut sum: Option<Scan> = None;
        for rep in 0..k_avg {
            let sc = noisy_bead_scene([c, c + 0.013], rb.d_nm, 30_000 + (s * k_avg + rep) as u64)?;
            let (scan, dt) = engine_scan(optics, &sc, d_avg)?;
            clock += dt / seeds as f64;
            sum = Some(match sum {
                None => scan,
                Some(mut a) => {
                    a.sx.data = &a.sx.data + &scan.sx.data;
                    a.sy.data = &a.sy.data + &scan.sy.data;
                    a
                }
            });
        }
        let mut a = sum.ok_or("no scans to average")?;
        a.sx.data.mapv_inplace(|v| v / k_avg as f64);
        a.sy.data.mapv_inplace(|v| v / k_avg as f64);
        let r = fit_beads(
            &a.sx,
            &a.sy,
            tpl,
            &FitOptions {
                init: Some(vec![BeadInit {
                    x: c,
                    y: c,
                    weight: 1.0,
                }]),
                ..FitOptions::default()
            },
        )
        .map_err(es)?;
        let b = r.beads[0];
        let we = b.weight_err.ok_or("bead fit without an uncertainty")?;
        e.push(mass_resolution_kda(we, rb.n, rb.density_g_cm3, &rb).map_err(es)?);
        m.push(b.weight * rb.mass_kda());
    }
    let (mean, scatter) = mean_std(&m);
    Ok(TradeRow {
        dwell_s: d_avg,
        scan_s: k_avg as f64 * d_avg * npix,
        clock_s: clock,
        sigma_fit: mean_std(&e).0,
        sigma_scatter: scatter,
        mean,
        sigma_protein_kda: f64::NAN,
        sigma_fit_sx_only: f64::NAN,
        found: m.len(),
        crlb: f64::NAN,
        estimators: vec![],
    })
}

/// Diameter (nm) of a protein cylinder of linear density `mu_mda_um` (eq. colDiam's cylinder
/// at protein density; the inverse of the microtubule's equivalent cylinder).
fn protein_cylinder_d_nm(mu_mda_um: f64) -> f64 {
    let da_per_nm3 = PROTEIN_DENSITY_G_CM3 * 1e-21 * quantities::DA_PER_G;
    let area_nm2 = mu_mda_um * 1e6 / 1000.0 / da_per_nm3;
    (4.0 * area_nm2 / std::f64::consts::PI).sqrt()
}

/// An 8 µm protein cylinder of diameter `d_nm` through (c, c) at `tilt_deg` from the y axis,
/// with `detector_noise` at the paper-noise level and the given seed.
fn microtubule_scene(c: f64, tilt_deg: f64, d_nm: f64, seed: u64) -> Result<Scene, String> {
    let mut sc = Scene::default();
    let t = tilt_deg.to_radians();
    let (dx, dy) = (4.0 * t.sin(), 4.0 * t.cos());
    sc.add_filament(Filament {
        points: vec![[c - dx, c - dy], [c + dx, c + dy]],
        z: 0.0,
        profile: DiameterProfile::Constant { d_nm },
        n: PROTEIN_N,
        spacing_nm: 50.0,
    })
    .map_err(|e| e.to_string())?;
    sc.effects.detector_noise = Some(DetectorNoise {
        sigma_sample: PAPER_DETECTOR_SIGMA_SAMPLE,
    });
    sc.seed = seed;
    Ok(sc)
}

/// The microtubule's rows by both methods: per dwell, `seeds` noisy scans of a
/// 13-protofilament microtubule along y through `c`, measured by the paper's per-row maxima
/// (`measure_filament`, Sec. 5) and by the whole-image bead-model fit (`fit_line_filament`) of
/// the same scans, each beside the Cramér–Rao bounds of the scan (`line_crlb` at the truth).
/// Returns (per-row rows, whole-image rows, the true linear density MDa/µm).
fn microtubule_rows(
    dwells: &[f64],
    seeds: usize,
    c: f64,
) -> Result<(Vec<TradeRow>, Vec<TradeRow>, f64), String> {
    let es = |e: crate::analysis::AnalysisError| e.to_string();
    let npix = (SCAN_PIXELS * SCAN_PIXELS) as f64;
    let o_mt = Optics {
        n_medium: 1.335,
        ..Optics::default()
    };
    let rb_mt = RefBead {
        n_medium: o_mt.n_medium,
        ..RefBead::default()
    };
    let tpl_mt =
        Template::from_optics(&o_mt, &DetectorModel::default(), rb_mt, 0.02, 0.0).map_err(es)?;
    let curve = AngleCurve::compute(&tpl_mt, &AngleCurveOptions::default()).map_err(es)?;
    let mo = MeasureOptions::default();
    let cal = LinDensCalib::from_template(
        &tpl_mt,
        PROTEIN_N,
        PROTEIN_DENSITY_G_CM3,
        PIXEL_UM,
        &mo,
        &BeadModelOptions::default(),
    )
    .map_err(es)?;
    let mt_true_mu = 13.0 * quantities::PROTOFILAMENT_MDA_PER_UM;
    let d_true = mt_equivalent_d_nm(13);
    let tilt_deg = 2.0;
    // the truth as the line model sees it, for the bound
    let truth = LineFilament {
        centre: [c, c],
        offset_um: 0.0,
        angle_deg: tilt_deg,
        lambda: lambda_of_diameter(&tpl_mt, d_true, PROTEIN_N).map_err(es)?,
        background: [0.0, 0.0],
        spacing_um: 0.05,
    };
    let mu_of_lambda = |lambda: f64| -> Result<f64, String> {
        Ok(mass_kda(
            volume_per_um(&tpl_mt, lambda, PROTEIN_N).map_err(es)?,
            PROTEIN_DENSITY_G_CM3,
        ) / 1000.0)
    };
    let axis = scan_axis();
    let (mut per_row, mut whole) = (vec![], vec![]);
    for (i, &dwell) in dwells.iter().enumerate() {
        let (mut mu, mut e, mut clock) = (vec![], vec![], 0.0);
        let (mut ang, mut ang_e, mut corr, mut corr_e) = (vec![], vec![], vec![], vec![]);
        let (mut w_mu, mut w_mu_e, mut w_ang, mut w_ang_e) = (vec![], vec![], vec![], vec![]);
        for s in 0..seeds {
            let sc = microtubule_scene(c, tilt_deg, d_true, 20_000 + 100 * i as u64 + s as u64)?;
            let (scan, dt) = engine_scan(&o_mt, &sc, dwell)?;
            clock += dt / seeds as f64;
            match measure_filament(&scan.sx, &scan.sy, &curve, &mo) {
                Ok(meas) => {
                    mu.push(cal.linear_density(meas.mean_corr.max(0.0)).map_err(es)?);
                    e.push(cal.linear_density(meas.sem_corr).map_err(es)?);
                    ang.push(meas.angle_deg);
                    ang_e.push(meas.angle_err_deg);
                    corr.push(meas.mean_corr);
                    corr_e.push(meas.sem_corr);
                }
                Err(_) => {
                    // too noisy to find the filament: no measurement at this dwell
                    for v in [
                        &mut mu,
                        &mut e,
                        &mut ang,
                        &mut ang_e,
                        &mut corr,
                        &mut corr_e,
                    ] {
                        v.push(f64::NAN);
                    }
                }
            }
            // the whole-image fit of the same scan, from its own matched-filter search
            match fit_line_filament(
                &scan.sx,
                &scan.sy,
                &tpl_mt,
                None,
                &LineFitOptions::default(),
            ) {
                Ok(r) if r.filament.lambda > 0.0 && r.filament.lambda.is_finite() => {
                    let m = mu_of_lambda(r.filament.lambda)?;
                    w_mu.push(m);
                    w_mu_e.push(m * r.err.lambda_rel);
                    w_ang.push(r.filament.angle_deg);
                    w_ang_e.push(r.err.angle_deg);
                }
                _ => {
                    for v in [&mut w_mu, &mut w_mu_e, &mut w_ang, &mut w_ang_e] {
                        v.push(f64::NAN);
                    }
                }
            }
        }
        let sigma = trade_pixel_sigma(dwell)?;
        let sig = |_: usize, _: usize, _: usize| Some(sigma);
        let bd = line_crlb(&tpl_mt, &truth, &axis, &axis, &[0, 1], &sig).map_err(es)?;
        let mu_crlb = bd.lambda_rel * mt_true_mu;
        let d_crlb = bd.diameter_rel * d_true;
        // diameters of the cylinders of the measured linear densities (σ_d/d = σ_μ/(2μ))
        let dia = |mu: &[f64], e: &[f64]| -> (Vec<f64>, Vec<f64>) {
            let d: Vec<f64> = mu.iter().map(|&m| protein_cylinder_d_nm(m)).collect();
            let de = d
                .iter()
                .zip(mu.iter().zip(e))
                .map(|(d, (m, e))| d * e / (2.0 * m))
                .collect();
            (d, de)
        };
        // the sensitivity relative to its mean over the seeds, % (its bound is λ's relative one)
        let cm = mean_std(&corr).0;
        let rel = |v: &[f64]| -> Vec<f64> { v.iter().map(|x| 100.0 * x / cm).collect() };
        let (d_pr, d_pr_e) = dia(&mu, &e);
        let (d_w, d_w_e) = dia(&w_mu, &w_mu_e);
        per_row.push(TradeRow {
            crlb: mu_crlb,
            estimators: vec![
                Efficiency::of("filament angle", "°", &ang, &ang_e, bd.angle_deg),
                Efficiency::of(
                    "filament sensitivity (relative)",
                    "%",
                    &rel(&corr),
                    &rel(&corr_e),
                    100.0 * bd.lambda_rel,
                ),
                Efficiency::of("filament linear density", "MDa/µm", &mu, &e, mu_crlb),
                Efficiency::of("filament diameter", "nm", &d_pr, &d_pr_e, d_crlb),
            ],
            ..TradeRow::measured(dwell, npix, clock, &mu, &e)
        });
        whole.push(TradeRow {
            crlb: mu_crlb,
            estimators: vec![
                Efficiency::of("filament angle", "°", &w_ang, &w_ang_e, bd.angle_deg),
                Efficiency::of("filament linear density", "MDa/µm", &w_mu, &w_mu_e, mu_crlb),
                Efficiency::of("filament diameter", "nm", &d_w, &d_w_e, d_crlb),
            ],
            ..TradeRow::measured(dwell, npix, clock, &w_mu, &w_mu_e)
        });
    }
    Ok((per_row, whole, mt_true_mu))
}

/// Run both trade-offs: dwell sweeps of 64×64-pixel scans (50 nm) of a 110 nm polystyrene bead
/// (fit: one bead, both channels and Sx only, σ from the residuals) and of a 13-protofilament
/// microtubule along y (protein cylinder, n = 1.587, in buffer n_s = 1.335; linear density from
/// the per-row maximum sensitivities, Sec. 5), `seeds` noise realisations per dwell.
pub fn tradeoff(quick: bool) -> Result<Tradeoff, String> {
    let dwells: &[f64] = if quick {
        &[1e-4, 1e-3, 1e-2, 1e-1]
    } else {
        &[1e-4, 3e-4, 1e-3, 3e-3, 1e-2, 3e-2, 1e-1, 3e-1]
    };
    let seeds = if quick { 2 } else { 64 };
    let es = |e: crate::analysis::AnalysisError| e.to_string();

    // --- bead
    let optics = Optics::default();
    let rb = RefBead::default();
    let tpl =
        Template::from_optics(&optics, &DetectorModel::default(), rb, 0.02, 0.0).map_err(es)?;
    let c = SCAN_PIXELS as f64 * PIXEL_UM / 2.0;
    let bead = bead_rows(&optics, &tpl, rb, dwells, seeds, c)?;
    let (k_avg, d_avg) = (4usize, 0.025);
    let averaged = averaged_row(&optics, &tpl, rb, k_avg, d_avg, seeds, c)?;
    let (microtubule, microtubule_fit, mt_true_mu) = microtubule_rows(dwells, seeds, c)?;
    let all_found = |rows: &[TradeRow]| -> Vec<TradeRow> {
        rows.iter().filter(|r| r.found == seeds).cloned().collect()
    };
    Ok(Tradeoff {
        mt_fit_k: sqrt_law(&all_found(&microtubule_fit), |r| r.sigma_fit),
        bead_crlb_k: sqrt_law(&bead, |r| r.crlb),
        mt_crlb_k: sqrt_law(&microtubule, |r| r.crlb),
        bead_k_kda_sqrt_s: sqrt_law(&bead, |r| r.sigma_fit),
        bead_k_sx_only: sqrt_law(&bead, |r| r.sigma_fit_sx_only),
        bead_k_protein: sqrt_law(&bead, |r| r.sigma_protein_kda),
        mt_k: sqrt_law(&all_found(&microtubule), |r| r.sigma_fit),
        bead,
        microtubule,
        microtubule_fit,
        seeds,
        mt_true_mu,
        template_integral: template_integral(&tpl, 0.02),
        ref_mass_kda: rb.mass_kda(),
        averaged,
        averaged_scans: k_avg,
    })
}

/// The dwell knob for the accuracy report: 1σ mass of the 110 nm bead (kDa) against the scan
/// time on the virtual clock (dwell × pixels); default = the scan bindings' default dwell.
pub fn knob_dwell(t: &Tradeoff) -> Knob {
    let default_dwell = crate::acquire::plan::DEFAULT_DWELL_S;
    Knob {
        id: "dwell".into(),
        title: "Dwell per pixel (averaging), 110 nm bead, paper noise, 64×64 × 50 nm".into(),
        metric: "1σ mass of the bead from the fit (kDa, polystyrene)".into(),
        timed: "instrument time on the virtual clock: dwell × 4096 pixels".into(),
        reference: "the simulated bead's true mass (440.7 MDa); σ from the fit's residuals".into(),
        points: t
            .bead
            .iter()
            .map(|r| Point {
                setting: format!(
                    "dwell {} ({} samples)",
                    fmt_dwell(r.dwell_s),
                    (r.dwell_s * 1e5).round()
                ),
                value: r.dwell_s,
                error: r.sigma_fit,
                seconds: r.scan_s,
                is_default: (r.dwell_s - default_dwell).abs() < 1e-12,
            })
            .collect(),
    }
}

pub fn fmt_dwell(s: f64) -> String {
    super::fmt_scaled(
        s,
        &[
            (1e-3, 1e6, 0, "µs"),
            (1e-2, 1e3, 1, "ms"),
            (1.0, 1e3, 0, "ms"),
        ],
    )
}

/// One targeted protocol's seed study (`scripts/targeted_study.rhai`, run by
/// `script::targeted_study`): instrument time, σ over seeds and the Cramér–Rao bound of the
/// readings it took.
#[derive(Debug, Clone, Serialize)]
pub struct TargetedRow {
    /// `targeted::bead` or `targeted::filament`.
    pub protocol: String,
    /// Unit of the quantity (kDa: the bead's mass; MDa/µm: the linear density).
    pub unit: String,
    pub seeds: usize,
    /// The filament's stretch, µm (NaN for the bead).
    pub length_um: f64,
    pub truth: f64,
    pub mean: f64,
    /// Standard deviation of the estimates over the seeds.
    pub scatter: f64,
    /// Mean of the protocol's own 1σ.
    pub sigma_mean: f64,
    /// Mean Cramér–Rao bound of the readings taken (at each seed's fit).
    pub crlb_mean: f64,
    /// Instrument time (virtual clock, moves included), mean and maximum over the seeds, s.
    pub time_mean_s: f64,
    pub time_max_s: f64,
    /// Seeds whose result was flagged.
    pub flagged: usize,
}

impl TargetedRow {
    /// The row of `protocol` ("bead" or "filament") from the study's JSON map; None when the
    /// study did not run it.
    pub fn from_study(study: &serde_json::Value, protocol: &str) -> Result<Option<Self>, String> {
        let Some(v) = study.get(protocol) else {
            return Ok(None);
        };
        let f = |k: &str| -> Result<f64, String> {
            v.get(k)
                .and_then(|x| x.as_f64())
                .ok_or_else(|| format!("targeted study: {protocol}.{k} missing or not a number"))
        };
        Ok(Some(Self {
            protocol: format!("targeted::{protocol}"),
            unit: v
                .get("unit")
                .and_then(|u| u.as_str())
                .unwrap_or("")
                .to_string(),
            seeds: f("seeds")? as usize,
            length_um: f("length_um").unwrap_or(f64::NAN),
            truth: f("truth")?,
            mean: f("mean")?,
            scatter: f("scatter")?,
            sigma_mean: f("sigma_mean")?,
            crlb_mean: f("crlb_mean")?,
            time_mean_s: f("time_mean_s")?,
            time_max_s: f("time_max_s")?,
            flagged: f("flagged")? as usize,
        }))
    }

    /// σ observed over the seeds ÷ mean CRLB (NaN with fewer than 2 seeds).
    pub fn efficiency(&self) -> f64 {
        if self.seeds < 2 {
            f64::NAN
        } else {
            self.scatter / self.crlb_mean
        }
    }

    /// (mean − truth) in units of the scatter (NaN with fewer than 2 seeds).
    pub fn bias_sigma(&self) -> f64 {
        if self.seeds < 2 {
            f64::NAN
        } else {
            (self.mean - self.truth) / self.scatter
        }
    }
}
