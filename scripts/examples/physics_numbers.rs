//! Prints the physics numbers quoted in docs/physics.md (run: cargo run --release --example physics_numbers).
use bfpscope::optics::calc::*;
use bfpscope::optics::finite_size::*;
use bfpscope::optics::params::Optics;
use bfpscope::optics::rayleigh::*;

fn main() {
    let o = Optics::default();
    let det = Detection::new(&o, &DetectorModel::default()).unwrap();
    let a110 = alpha_um3(110.0, 1.572, o.n_medium);
    let mut peak: (f64, f64) = (0.0, 0.0);
    for i in 0..2000 {
        let x = i as f64 * 0.0005;
        let v = det.response_unit(x, 0.0, 0.0).0[0] * a110;
        if v > peak.1 {
            peak = (x, v);
        }
    }
    println!(
        "110 nm PS bead: alpha = {a110:.4e} um^3; peak Sx/P = {:.4e} at x = {:.3} um",
        peak.1, peak.0
    );
    let s0 = det.response_unit(0.0, 0.0, 0.0).1[0] * a110;
    println!(
        "  dSx/dx at 0 = {s0:.4e} per um; Gittes-Schmidt full-collection paraxial slope = {:.4e}",
        16.0 / std::f64::consts::PI.sqrt() * o.k_per_um() * a110 / o.w0_um().powi(3)
    );
    // focus tolerance: sensitivity at x=y=0 vs z
    let (smax, zopt) = max_sensitivity_unit(&det, None, 6);
    let mut lo = zopt;
    while det.response_unit(0.0, 0.0, lo).1[0] > 0.98 * smax {
        lo -= 0.001;
    }
    let mut hi = zopt;
    while det.response_unit(0.0, 0.0, hi).1[0] > 0.98 * smax {
        hi += 0.001;
    }
    println!("  best focus z = {zopt:.4} um; sensitivity within 2% of max for z in [{lo:.3}, {hi:.3}] um");
    println!(
        "P_scat/P_beam (110 nm PS) = {:.3e}",
        p_scat_ratio(&o, 110.0, 1.572).unwrap()
    );
    let r = p_scat_ratio(&o, 110.0, 1.572).unwrap();
    println!(
        "  diameter where it reaches 1%: {:.0} nm",
        110.0 * (1e-2 / r).powf(1.0 / 6.0)
    );
    println!(
        "trap depth sphere 110 nm PS: {:.3} kT (T = {ROOM_T_K} K)",
        trap_depth_kt(&o, TrapShape::Sphere, 110.0, 1.572, ROOM_T_K).unwrap()
    );
    for d in [25.0, 50.0, 100.0, 150.0] {
        println!(
            "trap depth collagen fibril {d} nm (n = 1.414): {:.3} kT",
            trap_depth_kt(&o, TrapShape::Cylinder, d, 1.414, ROOM_T_K).unwrap()
        );
    }
    println!(
        "mass 110 nm PS bead: {:.1} MDa",
        sphere_mass_kda(110.0, 1.05).unwrap() / 1e3
    );
    println!(
        "n_corr collagen 1.414 vs PS 1.57 in 1.333: {:.4}",
        n_corr(1.414, 1.57, 1.333).unwrap()
    );
    println!(
        "n_corr protein 1.587 vs PS 1.57 in 1.335: {:.4}",
        n_corr(1.587, 1.57, 1.335).unwrap()
    );
    // finite size
    let (p, _) = max_sensitivity_unit(&det, None, 6);
    let f = |d: f64| max_sensitivity_unit(&det, Some(d), 6).0 / p;
    let bisect = |target: f64| {
        let (mut a, mut b) = (10.0, 1000.0);
        for _ in 0..30 {
            let m = 0.5 * (a + b);
            if 1.0 - f(m) < target {
                a = m
            } else {
                b = m
            }
        }
        0.5 * (a + b)
    };
    println!(
        "finite size: departs from d^3 by 1% at d = {:.0} nm, by 10% at d = {:.0} nm",
        bisect(0.01),
        bisect(0.10)
    );
    for d in [110.0, 160.0, 240.0, 500.0] {
        println!("  d = {d}: finite/point = {:.4}", f(d));
    }
}
