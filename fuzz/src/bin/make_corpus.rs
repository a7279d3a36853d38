//! Writes the seed inputs to `corpus/` (run from `fuzz/`): frames to `corpus/decode_frames/`,
//! volume files to `corpus/volume_<format>/`.
use tetwave_fuzz::volume::{seeds, Target};

fn write(dir: &std::path::Path, inputs: &[Vec<u8>]) {
    std::fs::create_dir_all(dir).unwrap();
    for (i, f) in inputs.iter().enumerate() {
        std::fs::write(dir.join(format!("seed-{i:02}")), f).unwrap();
    }
    println!("{} seeds in {}", inputs.len(), dir.display());
}

fn main() {
    write(
        std::path::Path::new("corpus/decode_frames"),
        &tetwave_fuzz::seed_frames(),
    );
    for t in Target::ALL {
        let dir = format!("corpus/volume_{}", t.name());
        write(std::path::Path::new(&dir), &seeds(t));
    }
}
