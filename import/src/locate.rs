//! Point location in an unstructured tet mesh: a uniform grid of the tets' bounding boxes and
//! barycentric interpolation. `prepare` samples a mesh with it onto the semi-regular mesh; the
//! viewer samples a mesh file onto the coarse proxy it draws in motion.

use crate::clean::{bbox, BoundaryDistance, ScalarTetMesh};

/// Point location in a tet mesh: a uniform grid over the bounding box whose cells list the tets whose
/// bounding boxes overlap them (about one tet per cell), and per tet the affine map to barycentric
/// coordinates.
pub struct Locator {
    lo: [f64; 3],
    inv_cell: [f64; 3],
    res: [usize; 3],
    cell_start: Vec<u32>,
    cell_tets: Vec<u32>,
    /// Per tet: rows of the inverse of `[x1−x0, x2−x0, x3−x0]` and `x0`.
    bary: Vec<([[f64; 3]; 3], [f64; 3])>,
    tets: Vec<[u32; 4]>,
    values: Vec<f64>,
    /// Tolerance on barycentric coordinates for points on faces.
    eps: f64,
    /// For `--field distance`: the boundary, to which the distance is computed at each point.
    boundary: Option<BoundaryDistance>,
}

impl Locator {
    pub fn new(mesh: &ScalarTetMesh) -> Self {
        let (lo, hi) = bbox(&mesh.points);
        let ext = [0, 1, 2].map(|a| (hi[a] - lo[a]).max(1e-300));
        let n = mesh.tets.len().max(1) as f64;
        let vol = ext[0] * ext[1] * ext[2];
        let h = (vol / n).cbrt();
        let res = [0, 1, 2].map(|a| ((ext[a] / h).ceil() as usize).clamp(1, 1024));
        let inv_cell = [0, 1, 2].map(|a| res[a] as f64 / ext[a]);
        let ncell = res[0] * res[1] * res[2];
        let cell_of = |x: f64, a: usize| {
            (((x - lo[a]) * inv_cell[a]).floor().max(0.0) as usize).min(res[a] - 1)
        };
        let tet_cells = |t: &[u32; 4]| {
            let mut tlo = [f64::INFINITY; 3];
            let mut thi = [f64::NEG_INFINITY; 3];
            for &v in t {
                let p = mesh.points[v as usize];
                for a in 0..3 {
                    tlo[a] = tlo[a].min(p[a]);
                    thi[a] = thi[a].max(p[a]);
                }
            }
            (
                [0, 1, 2].map(|a| cell_of(tlo[a], a)),
                [0, 1, 2].map(|a| cell_of(thi[a], a)),
            )
        };
        let mut count = vec![0u32; ncell + 1];
        for t in &mesh.tets {
            let (c0, c1) = tet_cells(t);
            for k in c0[2]..=c1[2] {
                for j in c0[1]..=c1[1] {
                    for i in c0[0]..=c1[0] {
                        count[i + res[0] * (j + res[1] * k) + 1] += 1;
                    }
                }
            }
        }
        for c in 1..=ncell {
            count[c] += count[c - 1];
        }
        let mut fill = count.clone();
        let mut cell_tets = vec![0u32; count[ncell] as usize];
        for (ti, t) in mesh.tets.iter().enumerate() {
            let (c0, c1) = tet_cells(t);
            for k in c0[2]..=c1[2] {
                for j in c0[1]..=c1[1] {
                    for i in c0[0]..=c1[0] {
                        let c = i + res[0] * (j + res[1] * k);
                        cell_tets[fill[c] as usize] = ti as u32;
                        fill[c] += 1;
                    }
                }
            }
        }
        let bary = mesh
            .tets
            .iter()
            .map(|t| {
                let p = |k: usize| mesh.points[t[k] as usize];
                let x0 = p(0);
                let c = [1, 2, 3].map(|k| [p(k)[0] - x0[0], p(k)[1] - x0[1], p(k)[2] - x0[2]]);
                // matrix M with columns c[0], c[1], c[2]; inverse rows
                (invert_columns(c), x0)
            })
            .collect();
        Locator {
            lo,
            inv_cell,
            res,
            cell_start: count,
            cell_tets,
            bary,
            tets: mesh.tets.clone(),
            values: mesh.values.clone(),
            eps: 1e-9,
            boundary: mesh
                .distance
                .then(|| BoundaryDistance::new(&mesh.points, &mesh.tets)),
        }
    }

    /// Interpolated value at `p` (with `distance`, the distance from `p` to the boundary), or
    /// `None` outside the mesh.
    pub fn sample(&self, p: [f64; 3]) -> Option<f64> {
        let mut c = [0usize; 3];
        for a in 0..3 {
            let x = (p[a] - self.lo[a]) * self.inv_cell[a];
            if !(x >= -1e-9 * self.res[a] as f64 && x <= self.res[a] as f64 * (1.0 + 1e-9)) {
                return None;
            }
            c[a] = (x.floor().max(0.0) as usize).min(self.res[a] - 1);
        }
        let cell = c[0] + self.res[0] * (c[1] + self.res[1] * c[2]);
        let (s, e) = (
            self.cell_start[cell] as usize,
            self.cell_start[cell + 1] as usize,
        );
        let mut best: Option<(f64, usize, [f64; 4])> = None;
        for &ti in &self.cell_tets[s..e] {
            let (inv, x0) = &self.bary[ti as usize];
            let d = [p[0] - x0[0], p[1] - x0[1], p[2] - x0[2]];
            let l1 = inv[0][0] * d[0] + inv[0][1] * d[1] + inv[0][2] * d[2];
            let l2 = inv[1][0] * d[0] + inv[1][1] * d[1] + inv[1][2] * d[2];
            let l3 = inv[2][0] * d[0] + inv[2][1] * d[1] + inv[2][2] * d[2];
            let l = [1.0 - l1 - l2 - l3, l1, l2, l3];
            let worst = l.iter().fold(f64::INFINITY, |m, &x| m.min(x));
            if worst >= 0.0 {
                best = Some((worst, ti as usize, l));
                break;
            }
            if worst >= -self.eps && best.is_none_or(|b| worst > b.0) {
                best = Some((worst, ti as usize, l));
            }
        }
        let (_, ti, l) = best?;
        if let Some(b) = &self.boundary {
            return Some(b.distance(p));
        }
        let t = self.tets[ti];
        let l = l.map(|x| x.max(0.0));
        let sum: f64 = l.iter().sum();
        Some(
            (0..4)
                .map(|k| l[k] * self.values[t[k] as usize])
                .sum::<f64>()
                / sum,
        )
    }
}

/// Inverse of the 3×3 matrix whose columns are `c`, as rows.
fn invert_columns(c: [[f64; 3]; 3]) -> [[f64; 3]; 3] {
    // M = [c0 c1 c2]; M^{-1} rows are (c1×c2, c2×c0, c0×c1) / det
    let cross = |a: [f64; 3], b: [f64; 3]| {
        [
            a[1] * b[2] - a[2] * b[1],
            a[2] * b[0] - a[0] * b[2],
            a[0] * b[1] - a[1] * b[0],
        ]
    };
    let r0 = cross(c[1], c[2]);
    let r1 = cross(c[2], c[0]);
    let r2 = cross(c[0], c[1]);
    let det = c[0][0] * r0[0] + c[0][1] * r0[1] + c[0][2] * r0[2];
    let inv = 1.0 / det;
    [
        r0.map(|x| x * inv),
        r1.map(|x| x * inv),
        r2.map(|x| x * inv),
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cube6() -> ScalarTetMesh {
        let (points, tets) = tetwave_protocol::shapes::box6([0.0; 3], [1.0; 3]);
        let values = points
            .iter()
            .map(|p| p[0] + 2.0 * p[1] + 3.0 * p[2])
            .collect();
        ScalarTetMesh {
            points,
            tets,
            values,
            distance: false,
        }
    }

    #[test]
    fn locates_and_interpolates_linear_field_exactly() {
        let loc = Locator::new(&cube6());
        for i in 0..=10 {
            for j in 0..=10 {
                for k in 0..=10 {
                    let p = [i as f64 / 10.0, j as f64 / 10.0, k as f64 / 10.0];
                    let v = loc.sample(p).expect("inside");
                    assert!((v - (p[0] + 2.0 * p[1] + 3.0 * p[2])).abs() < 1e-12);
                }
            }
        }
        assert_eq!(loc.sample([1.5, 0.5, 0.5]), None);
        assert_eq!(loc.sample([-0.1, 0.5, 0.5]), None);
    }
}
