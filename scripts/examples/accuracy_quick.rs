fn main() {
    let quick = std::env::args().any(|a| a == "--quick");
    for k in bfpscope::accuracy::physics_knobs(quick) {
        println!("{}", bfpscope::accuracy::markdown_table(&k));
    }
}
