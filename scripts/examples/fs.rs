use bfpscope::optics::{finite_size::*, params::Optics, rayleigh::*};
fn main() {
    let det = Detection::new(&Optics::default(), &DetectorModel::default()).unwrap();
    let (p, zp) = max_sensitivity_unit(&det, None, 6);
    println!("point: sens {p:.5e} at z = {zp:.4}");
    for d in [
        50.0, 110.0, 160.0, 200.0, 240.0, 300.0, 400.0, 500.0, 700.0, 1000.0,
    ] {
        let t = std::time::Instant::now();
        let (s, z) = max_sensitivity_unit(&det, Some(d), 6);
        let (s8, _) = max_sensitivity_unit(&det, Some(d), 9);
        println!(
            "d={d}: ratio {:.5} (n_r 9: {:.5}) z={z:.3} {:?}",
            s / p,
            s8 / p,
            t.elapsed()
        );
    }
}
