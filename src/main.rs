fn main() {
    println!("bfpscope: workbench lands with the CLI");
}
