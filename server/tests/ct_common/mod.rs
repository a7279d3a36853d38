//! A CT-like test volume shared by the tests of preparing by parts.

/// A CT-like field over `dims` voxels (x fastest), about 190 to 1170: smooth structure, a dense
/// shell with sharp edges, and noise at every voxel (a seeded LCG).
pub fn ct_field(dims: [usize; 3]) -> Vec<f32> {
    let mut v = Vec::with_capacity(dims.iter().product());
    let mut noise = 12345u32;
    for k in 0..dims[2] {
        for j in 0..dims[1] {
            for i in 0..dims[0] {
                noise = noise.wrapping_mul(1664525).wrapping_add(1013904223);
                let (x, y, z) = (
                    i as f32 / dims[0] as f32 - 0.5,
                    j as f32 / dims[1] as f32 - 0.5,
                    k as f32 / dims[2] as f32 - 0.5,
                );
                let r = (x * x + y * y + 0.5 * z * z).sqrt();
                let shell = if (0.3..0.36).contains(&r) { 900.0 } else { 0.0 };
                let soft = 40.0 * (9.0 * x).sin() * (7.0 * y).cos() + 30.0 * z;
                v.push(200.0 + shell + soft + (noise >> 24) as f32 * 0.1);
            }
        }
    }
    v
}
