use bfpscope::optics::{params::Optics, rayleigh::*};
fn main() {
    let pts = [
        (0.1, 0.0, 0.0),
        (0.3, 0.2, 0.0),
        (0.8, -0.5, 0.3),
        (1.2, 0.4, -0.5),
        (0.0, 0.0, 0.7),
        (2.0, 1.0, 1.5),
    ];
    let r = Detection::new(
        &Optics {
            n_theta: 128,
            n_phi: 64,
            ..Optics::default()
        },
        &DetectorModel::default(),
    )
    .unwrap();
    let peak = r.response_unit(0.25, 0.0, 0.0).0[0].abs();
    for (nt, np) in [(12, 6), (16, 8), (24, 12), (32, 16), (48, 24), (64, 32)] {
        let d = Detection::new(
            &Optics {
                n_theta: nt,
                n_phi: np,
                ..Optics::default()
            },
            &DetectorModel::default(),
        )
        .unwrap();
        let mut worst: f64 = 0.0;
        for &(x, y, z) in &pts {
            let a = d.response_unit(x, y, z).0;
            let b = r.response_unit(x, y, z).0;
            for c in 0..3 {
                worst = worst.max((a[c] - b[c]).abs() / peak);
            }
        }
        println!("n_theta={nt} n_phi={np}: worst {worst:.2e}");
    }
}
