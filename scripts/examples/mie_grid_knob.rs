//! Accuracy vs cost of the focused-beam Mie response's incident plane-wave grid
//! (`accuracy::mie_knobs::knob_mie_grid`, the `mie_grid` knob for the accuracy report): prints a markdown
//! table. Run: `cargo run --release --example mie_grid_knob [-- --full]`.

fn main() {
    let full = std::env::args().any(|a| a == "--full");
    let k = bfpscope::accuracy::mie_knobs::knob_mie_grid(!full);
    println!(
        "{} — error: {}; time: {}; reference: {}",
        k.title, k.metric, k.timed, k.reference
    );
    println!("| grid | error | µs per point |");
    println!("|---|---|---|");
    for p in &k.points {
        println!(
            "| {}{} | {:.1e} | {:.0} |",
            p.setting,
            if p.is_default { " (default)" } else { "" },
            p.error,
            p.seconds * 1e6
        );
    }
}
