//! Writes the seed frames to `corpus/decode_frames/` (run from `fuzz/`).
fn main() {
    let dir = std::path::Path::new("corpus/decode_frames");
    std::fs::create_dir_all(dir).unwrap();
    for (i, f) in tetwave_fuzz::seed_frames().iter().enumerate() {
        std::fs::write(dir.join(format!("seed-{i:02}")), f).unwrap();
    }
    println!(
        "{} seeds in {}",
        tetwave_fuzz::seed_frames().len(),
        dir.display()
    );
}
