//! Where does the point dipole depart from the focused-beam Mie tier? Absolute maximum
//! sensitivity of the Mie tier over the point dipole's (paraxial Rayleigh tier, with and without
//! the `polarization` flag), vs d; and the cost of one Mie tier.
use bfpscope::optics::finite_size::max_sensitivity_unit;
use bfpscope::optics::mie::Complex64;
use bfpscope::optics::mie_beam::{MieBeam, MieBeamSpec};
use bfpscope::optics::params::Optics;
use bfpscope::optics::rayleigh::{alpha_um3, Detection, DetectorModel};
use std::time::Instant;

fn main() {
    let o = Optics::default();
    println!("{o:?}");
    let spec = MieBeamSpec::default();
    let d0 = Detection::new(&o, &DetectorModel::default()).unwrap();
    let dp = Detection::new(
        &o,
        &DetectorModel {
            polarization: true,
            misalignment: None,
        },
    )
    .unwrap();
    let r0 = max_sensitivity_unit(&d0, None, 1).0;
    let rp = max_sensitivity_unit(&dp, None, 1).0;
    println!(
        "rayleigh scalar {r0:.5e} polarized {rp:.5e} ratio {:.4}",
        rp / r0
    );
    for &n in &[1.45, 1.572, 2.0] {
        let nc = Complex64::new(n, 0.0);
        for d in [10.0, 30.0, 60.0, 110.0, 170.0, 210.0, 250.0, 300.0] {
            let t = Instant::now();
            let m = MieBeam::new(&o, d, nc, spec).unwrap().max_sensitivity_x().0;
            let a = alpha_um3(d, n, o.n_medium);
            println!(
                "n {n:.3} d {d:5.0} mie/ray(scalar) {:.4} mie/ray(pol) {:.4} ({:.0} ms)",
                m / (a * r0),
                m / (a * rp),
                t.elapsed().as_secs_f64() * 1e3
            );
        }
    }
}
