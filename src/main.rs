fn main() {
    println!("flashmat");
}
