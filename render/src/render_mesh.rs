//! The leaf mesh as the renderers see it: positions, tets, one scalar per vertex and, for a
//! domain that does not fill the mesh, one level-set value per vertex.

use glam::DVec3;
use tetwave_protocol::hierarchy::LevelWalker;
use tetwave_protocol::shapes;
use tetwave_protocol::BaseMesh;

#[derive(Debug, Clone, PartialEq)]
pub struct RenderMesh {
    pub positions: Vec<[f64; 3]>,
    pub tets: Vec<[u32; 4]>,
    pub values: Vec<f32>,
    /// Scalar range mapped to the transfer function's `[0, 1]`.
    pub value_range: (f32, f32),
    /// Per vertex, the domain's level set (the signed distance to its boundary, positive
    /// inside), or `None` when the whole mesh is domain. Renderers interpolate it linearly in each
    /// tet like the scalar and draw only where it is ≥ 0: a tet that straddles the boundary
    /// contributes the part of each ray segment inside the domain.
    pub levelset: Option<Vec<f32>>,
}

impl RenderMesh {
    pub fn new(positions: Vec<[f64; 3]>, tets: Vec<[u32; 4]>, values: Vec<f32>) -> Self {
        let (lo, hi) = values
            .iter()
            .fold((f32::INFINITY, f32::NEG_INFINITY), |(l, h), &v| {
                (l.min(v), h.max(v))
            });
        let value_range = if lo.is_finite() { (lo, hi) } else { (0.0, 1.0) };
        RenderMesh {
            positions,
            tets,
            values,
            value_range,
            levelset: None,
        }
    }

    /// The uniform level-`level` leaf mesh of a hierarchy whose finest-level vertex values (indexed by
    /// vertex key, as `synthesize_all` returns them) are `values`. Tets outside the input domain are
    /// left out at every level: empty base tets, children a node marks empty (`empty_children[id]`,
    /// bit `i` for child `i`; ids past the slice's end mark nothing) and everything below them.
    pub fn uniform_level(
        base: &BaseMesh,
        values: &[f32],
        empty_children: &[u8],
        level: u8,
    ) -> Self {
        Self::uniform_level_clipped(base, values, empty_children, level, None)
    }

    /// [`Self::uniform_level`] with the domain's level set at the finest vertices (by vertex key,
    /// as a store's `levelset.f32` holds it): each vertex of the level keeps its own value (the
    /// level set restricted to the level's vertices, so a coarse level sees a coarser boundary),
    /// and tets whose 4 corners are all outside (< 0) are left out, as nothing of them is drawn.
    pub fn uniform_level_clipped(
        base: &BaseMesh,
        values: &[f32],
        empty_children: &[u8],
        level: u8,
        levelset: Option<&[f32]>,
    ) -> Self {
        let keys = base.vertex_keys();
        let forest = base.forest();
        let level = level.min(forest.levels);
        let empty = empty_at_level(base, empty_children, level);
        let start = forest.level_start(level);
        let mut remap = std::collections::HashMap::new();
        let mut positions = Vec::new();
        let mut vals = Vec::new();
        let mut lset = Vec::new();
        let mut tets = Vec::new();
        for (id, t) in LevelWalker::level(forest, level) {
            if empty[(id - start) as usize] {
                continue;
            }
            let k: [u64; 4] = std::array::from_fn(|i| keys.key(t.base, &t.v[i]));
            if let Some(ls) = levelset {
                if k.iter().all(|&k| ls[k as usize] < 0.0) {
                    continue;
                }
            }
            let mut tet = [0u32; 4];
            for (i, w) in t.v.iter().enumerate() {
                tet[i] = *remap.entry(k[i]).or_insert_with(|| {
                    positions.push(base.position(t.base, w));
                    vals.push(values[k[i] as usize]);
                    if let Some(ls) = levelset {
                        lset.push(ls[k[i] as usize]);
                    }
                    (positions.len() - 1) as u32
                });
            }
            tets.push(tet);
        }
        let mut m = RenderMesh::new(positions, tets, vals);
        m.levelset = levelset.map(|_| lset);
        m.value_range = {
            let (lo, hi) = values
                .iter()
                .fold((f32::INFINITY, f32::NEG_INFINITY), |(l, h), &v| {
                    (l.min(v), h.max(v))
                });
            (lo, hi)
        };
        m
    }

    /// `[0,1]^3 · size` cut into `n^3` cubes of 6 Kuhn tets each ([`shapes::kuhn_grid`]), positively
    /// oriented, with the scalar `f` at the points.
    pub fn kuhn_cube(n: usize, size: f64, f: impl Fn([f64; 3]) -> f64) -> Self {
        let (mut positions, mut tets) = shapes::kuhn_grid(n, |_, _, _| true);
        for p in &mut positions {
            *p = p.map(|c| c * size);
        }
        shapes::orient_positive(&positions, &mut tets);
        let values = positions.iter().map(|&p| f(p) as f32).collect();
        RenderMesh::new(positions, tets, values)
    }

    /// Writes the mesh as a legacy binary VTK unstructured grid (tets, and the values as point
    /// scalars `f`), for renderers outside tetwave (VTK's projected tetrahedra in the benchmarks).
    pub fn write_vtk(&self, path: &std::path::Path) -> std::io::Result<()> {
        use std::io::Write;
        let mut f = std::io::BufWriter::new(std::fs::File::create(path)?);
        writeln!(
            f,
            "# vtk DataFile Version 3.0\ntetwave\nBINARY\nDATASET UNSTRUCTURED_GRID"
        )?;
        writeln!(f, "POINTS {} double", self.positions.len())?;
        for c in self.positions.iter().flatten() {
            f.write_all(&c.to_be_bytes())?;
        }
        writeln!(f, "\nCELLS {} {}", self.tets.len(), self.tets.len() * 5)?;
        for t in &self.tets {
            f.write_all(&4i32.to_be_bytes())?;
            for v in t {
                f.write_all(&(*v as i32).to_be_bytes())?;
            }
        }
        writeln!(f, "\nCELL_TYPES {}", self.tets.len())?;
        for _ in &self.tets {
            f.write_all(&10i32.to_be_bytes())?;
        }
        writeln!(
            f,
            "\nPOINT_DATA {}\nSCALARS f float 1\nLOOKUP_TABLE default",
            self.positions.len()
        )?;
        for v in &self.values {
            f.write_all(&v.to_be_bytes())?;
        }
        writeln!(f)?;
        f.flush()
    }

    /// Swaps the last two vertices of negatively oriented tets.
    pub fn orient_positive(&mut self) {
        shapes::orient_positive(&self.positions, &mut self.tets);
    }

    pub fn bounds(&self) -> (DVec3, DVec3) {
        let mut lo = DVec3::splat(f64::INFINITY);
        let mut hi = DVec3::splat(f64::NEG_INFINITY);
        for p in &self.positions {
            let v = DVec3::from_array(*p);
            lo = lo.min(v);
            hi = hi.max(v);
        }
        (lo, hi)
    }

    pub fn center(&self) -> DVec3 {
        let (lo, hi) = self.bounds();
        (lo + hi) * 0.5
    }

    /// Bounding-box diagonal: the length unit of transfer-function extinction.
    pub fn diagonal(&self) -> f64 {
        let (lo, hi) = self.bounds();
        (hi - lo).length().max(1e-300)
    }

    /// Normalized scalar of a raw value.
    #[inline]
    pub fn normalize(&self, v: f64) -> f64 {
        let (lo, hi) = (self.value_range.0 as f64, self.value_range.1 as f64);
        if hi > lo {
            (v - lo) / (hi - lo)
        } else {
            0.5
        }
    }

    /// Per tet, for ray casting: outward face planes `(n, d)` with `n·x = d` on face `i` (opposite
    /// vertex `i`) and the linear normalized scalar `s(x) = g·x + c`, all relative to `origin`. A
    /// degenerate tet (zero volume) gets zero planes and gradient: it contributes no length.
    pub fn tet_geometry(&self, t: usize, origin: DVec3) -> ([(DVec3, f64); 4], DVec3, f64) {
        let tet = self.tets[t];
        let x: [DVec3; 4] = tet.map(|v| DVec3::from_array(self.positions[v as usize]) - origin);
        let s: [f64; 4] = tet.map(|v| self.normalize(self.values[v as usize] as f64));
        let Some((g, c)) = linear_function(&x, s) else {
            return ([(DVec3::ZERO, 0.0); 4], DVec3::ZERO, s[0]);
        };
        let faces = [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]];
        let planes = std::array::from_fn(|i| {
            let [a, b, cc] = faces[i];
            let mut n = (x[b] - x[a]).cross(x[cc] - x[a]).normalize_or_zero();
            if n.dot(x[i] - x[a]) > 0.0 {
                n = -n;
            }
            (n, n.dot(x[a]))
        });
        (planes, g, c)
    }

    /// The tet's linear level set `φ(x) = g·x + c` (relative to `origin`), or `(0, 1)` (everywhere
    /// inside) when the mesh has no level set; a degenerate tet gets `(0, φ₀)`.
    pub fn tet_levelset(&self, t: usize, origin: DVec3) -> (DVec3, f64) {
        let Some(ls) = &self.levelset else {
            return (DVec3::ZERO, 1.0);
        };
        let tet = self.tets[t];
        let x: [DVec3; 4] = tet.map(|v| DVec3::from_array(self.positions[v as usize]) - origin);
        let l: [f64; 4] = tet.map(|v| ls[v as usize] as f64);
        linear_function(&x, l).unwrap_or((DVec3::ZERO, l[0]))
    }
}

/// The linear function `f(x) = g·x + c` taking the values `f[i]` at the tet's corners `x[i]`, or
/// `None` for a degenerate (near zero volume) or non-finite tet.
fn linear_function(x: &[DVec3; 4], f: [f64; 4]) -> Option<(DVec3, f64)> {
    let e1 = x[1] - x[0];
    let e2 = x[2] - x[0];
    let e3 = x[3] - x[0];
    let det = e1.dot(e2.cross(e3));
    let scale = e1.length().max(e2.length()).max(e3.length());
    if det.abs() <= 1e-14 * scale.powi(3) || !det.is_finite() {
        return None;
    }
    // gradient: solve [e1 e2 e3]^T g = (f1-f0, f2-f0, f3-f0)
    let inv = 1.0 / det;
    let r1 = e2.cross(e3) * inv;
    let r2 = e3.cross(e1) * inv;
    let r3 = e1.cross(e2) * inv;
    let g = r1 * (f[1] - f[0]) + r2 * (f[2] - f[0]) + r3 * (f[3] - f[0]);
    Some((g, f[0] - g.dot(x[0])))
}

/// The part of a ray segment where a level set that is linear along it, `l0` at its start and
/// `l1` at its end, is ≥ 0: `None` when there is none (both ends < 0), else the fractions
/// `(a, b)` of the segment where that part starts and ends (`0 ≤ a ≤ b ≤ 1`), at which the caller
/// interpolates its other linear quantities (position, scalar).
#[inline]
pub fn clip_to_levelset(l0: f64, l1: f64) -> Option<(f64, f64)> {
    match (l0 >= 0.0, l1 >= 0.0) {
        (true, true) => Some((0.0, 1.0)),
        (false, false) => None,
        // the zero of l0 + u·(l1 − l0): l0 and l1 have opposite signs, so l0 − l1 ≠ 0
        (false, true) => Some(((l0 / (l0 - l1)).clamp(0.0, 1.0), 1.0)),
        (true, false) => Some((0.0, (l0 / (l0 - l1)).clamp(0.0, 1.0))),
    }
}

/// Which tets of `level` lie outside the input domain (indexed from the level's first id): a base
/// tet flagged empty, or a child its parent node marks empty, or anything below either.
pub fn empty_at_level(base: &BaseMesh, empty_children: &[u8], level: u8) -> Vec<bool> {
    let forest = base.forest();
    let mut empty: Vec<bool> = (0..forest.level_len(0) as usize)
        .map(|i| base.empty.get(i).copied().unwrap_or(false))
        .collect();
    for k in 0..level.min(forest.levels) {
        let start = forest.level_start(k);
        let mut next = vec![false; forest.level_len(k + 1) as usize];
        for (j, &e) in empty.iter().enumerate() {
            let id = start + j as u64;
            let mask = empty_children.get(id as usize).copied().unwrap_or(0);
            let first = forest.child(id, 0) - forest.level_start(k + 1);
            for c in 0..8 {
                next[(first + c) as usize] = e || mask >> c & 1 == 1;
            }
        }
        empty = next;
    }
    empty
}
