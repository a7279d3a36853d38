//! What the grid examples share: reading a `(2^L + 1)³` f32 grid as bench-rd writes it, and the
//! box6 hierarchy whose vertices are its points.

use tetwave_protocol::shapes::box6;
use tetwave_protocol::BaseMesh;

/// The samples of `path`, a little-endian f32 grid of `(2^levels + 1)³` values, x fastest; exits
/// with a message naming `tool` when it cannot be read or has another size.
pub fn read_grid(tool: &str, path: &str, levels: u8) -> Vec<f32> {
    let n = (1usize << levels) + 1;
    let bytes = std::fs::read(path).unwrap_or_else(|e| {
        eprintln!("{tool}: {path}: {e}");
        std::process::exit(1)
    });
    if bytes.len() != n * n * n * 4 {
        eprintln!(
            "{tool}: {path} has {} bytes, a {n}³ f32 grid has {}",
            bytes.len(),
            n * n * n * 4
        );
        std::process::exit(1);
    }
    bytes
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect()
}

/// The unit cube's box6 base mesh refined `levels` times: its vertices, scaled by `2^levels`, are
/// the grid's points (values are not needed: the examples read the grid).
pub fn unit_box6(levels: u8) -> BaseMesh {
    let (positions, tets) = box6([0.0; 3], [1.0; 3]);
    BaseMesh {
        levels,
        values: vec![0.0; positions.len()],
        empty: vec![false; tets.len()],
        predictor: Default::default(),
        positions,
        tets,
    }
}
