//! Cleaning an imported mesh: the scalar choice (`--scalar NAME`, `NAME:mag`, `NAME:K`, cell arrays
//! averaged to the points volume-weighted, `--field distance`), NaN/Inf handling, orientation,
//! degenerate and duplicate tets, quality. `prepare` resamples what this returns; `tetwave render
//! <mesh>` draws it as it is.

use crate::{FieldArray, ImportedMesh, TetMesh};
use std::collections::{HashMap, HashSet};
use tetwave_protocol::base::signed_volume;

#[derive(Debug, thiserror::Error)]
pub enum CleanError {
    #[error("the mesh has no tetrahedra or other volume cells ({ignored} points, lines or surface cells ignored{unsupported}): a surface-only mesh has no volume to resample")]
    NoTets { ignored: usize, unsupported: String },
    #[error("the mesh has no point or cell arrays; pass --field distance to view its geometry (the distance to its boundary)")]
    NoScalars,
    #[error("no point or cell array named {name:?}; available: {available}")]
    UnknownScalar { name: String, available: String },
    #[error("array {name:?} has {components} components: {component:?} is not one (use {name}:mag or {name}:0..{last})", last = components - 1)]
    UnknownComponent {
        name: String,
        components: usize,
        component: String,
    },
    #[error("unknown --field {0:?} (known: distance)")]
    UnknownField(String),
    #[error("--field and --scalar exclude each other")]
    FieldAndScalar,
    #[error("scalar {name:?} has {count} NaN/Inf values (first at point {first}); pass --nan-as VALUE to replace them")]
    NonFinite {
        name: String,
        count: usize,
        first: usize,
    },
    #[error("point {index} has a non-finite coordinate")]
    BadPoint { index: usize },
    #[error("all {count} tets have zero volume")]
    AllDegenerate { count: usize },
}

/// Tets whose smallest dihedral angle is below this many degrees are counted as slivers.
pub const SLIVER_DEGREES: f64 = 5.0;

/// What cleaning did, for the summary.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct CleanReport {
    /// Points of the file (every point, used by a cell or not).
    pub points_read: usize,
    /// Cells of the file, of every kind.
    pub cells_read: usize,
    /// Tets before cleaning: the file's tets, corner tets of higher-order tets, split cells.
    pub tets_read: usize,
    pub tets_kept: usize,
    pub tets_reoriented: usize,
    /// Zero-volume and duplicate tets dropped.
    pub tets_dropped: usize,
    pub tets_dropped_degenerate: usize,
    pub tets_dropped_duplicate: usize,
    /// Points, lines, surface cells and volume cells of unsupported kinds.
    pub cells_ignored: usize,
    /// Volume cells of unsupported kinds (part of `cells_ignored`).
    pub cells_unsupported: usize,
    /// Hexahedra, wedges and pyramids split into tets.
    pub cells_split: usize,
    /// Higher-order tets reduced to their corner tet.
    pub cells_linearized: usize,
    /// The scalar: an array name, `name:mag` or `name:K` for a vector, or `distance`.
    pub scalar: String,
    /// `point`, `cell` (averaged to the points) or `geometric`.
    pub scalar_source: String,
    pub non_finite_replaced: usize,
    /// Smallest dihedral angle of the kept tets, in degrees.
    pub min_dihedral_deg: f64,
    /// Kept tets with a dihedral angle below [`SLIVER_DEGREES`].
    pub slivers: usize,
    /// What was done, in words.
    pub notes: Vec<String>,
    /// The mesh's arrays, in the order the default choice tries them (point scalars, point
    /// vectors, cell arrays).
    pub arrays: Vec<ArrayInfo>,
}

/// One array of the mesh, as `prepare --json` lists it.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ArrayInfo {
    pub name: String,
    /// `point` or `cell`.
    pub source: String,
    pub components: usize,
    /// Every value (the magnitude of a vector; on the tets' cells for a cell array) is the same.
    pub constant: bool,
}

/// A cleaned tet mesh with one scalar per point, ready for point location.
pub struct ScalarTetMesh {
    pub points: Vec<[f64; 3]>,
    pub tets: Vec<[u32; 4]>,
    pub values: Vec<f64>,
    /// The scalar is the distance to the boundary (`--field distance`): `prepare`'s point locator computes it at
    /// each sampled point instead of interpolating `values`, which are zero at every vertex of a
    /// mesh whose vertices all lie on its boundary.
    pub distance: bool,
}

/// How the scalar is chosen.
#[derive(Debug, Clone, Copy, Default)]
pub struct ImportOptions<'a> {
    /// `NAME`, `NAME:mag` or `NAME:K` among point and cell arrays; the first point scalar when
    /// absent (then the first point vector's magnitude, the first cell array).
    pub scalar: Option<&'a str>,
    /// A geometric field instead of an array: `distance` (to the boundary).
    pub field: Option<&'a str>,
    pub nan_as: Option<f64>,
}

/// Picks the scalar, checks for NaN/Inf, re-orients inverted tets and drops zero-volume ones.
pub fn clean(
    mesh: TetMesh,
    scalar: Option<&str>,
    nan_as: Option<f64>,
) -> Result<(ScalarTetMesh, CleanReport), CleanError> {
    clean_import(
        mesh.into(),
        &ImportOptions {
            scalar,
            field: None,
            nan_as,
        },
    )
}

/// A component of a vector array.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Component {
    Magnitude,
    Index(usize),
}

/// The chosen array.
enum Choice<'m> {
    Point(&'m str, &'m [f64], usize, Option<Component>),
    Cell(&'m FieldArray, Option<Component>),
}

/// Values of one component (or the magnitude, or the only component) of tuples of `nc` values.
/// The magnitude is the Euclidean norm of a vector and the Frobenius norm of a tensor: a
/// 6-component tuple is a symmetric tensor stored as (xx, yy, zz, xy, yz, xz), VTK's order, whose
/// off-diagonal terms count twice.
fn component(values: &[f64], nc: usize, c: Option<Component>) -> Vec<f64> {
    match c {
        None | Some(Component::Index(_)) if nc == 1 => values.to_vec(),
        Some(Component::Index(k)) => values.chunks_exact(nc).map(|t| t[k]).collect(),
        None | Some(Component::Magnitude) if nc == 6 => values
            .chunks_exact(6)
            .map(|t| {
                let diag = t[0] * t[0] + t[1] * t[1] + t[2] * t[2];
                let off = t[3] * t[3] + t[4] * t[4] + t[5] * t[5];
                (diag + 2.0 * off).sqrt()
            })
            .collect(),
        None | Some(Component::Magnitude) => values
            .chunks_exact(nc)
            .map(|t| t.iter().map(|x| x * x).sum::<f64>().sqrt())
            .collect(),
    }
}

fn parse_component(name: &str, nc: usize, spec: &str) -> Result<Option<Component>, CleanError> {
    let c = match spec.to_ascii_lowercase().as_str() {
        "mag" | "magnitude" | "norm" => Component::Magnitude,
        "x" => Component::Index(0),
        "y" => Component::Index(1),
        "z" => Component::Index(2),
        s => match s.parse::<usize>() {
            Ok(k) => Component::Index(k),
            Err(_) => Component::Index(usize::MAX),
        },
    };
    match c {
        Component::Index(k) if k >= nc => Err(CleanError::UnknownComponent {
            name: name.to_string(),
            components: nc,
            component: spec.to_string(),
        }),
        c => Ok(Some(c)),
    }
}

fn available(m: &ImportedMesh) -> String {
    let mut out = Vec::new();
    let vector = |a: &FieldArray, kind: &str| {
        format!(
            "{n} ({kind}, {c} components: {n}:mag, {n}:0..{last})",
            n = a.name,
            c = a.components,
            last = a.components - 1
        )
    };
    for a in &m.mesh.point_data {
        out.push(format!("{} (point)", a.name));
    }
    for a in &m.point_vectors {
        out.push(vector(a, "point"));
    }
    for a in &m.cell_data {
        if a.components == 1 {
            out.push(format!("{} (cell)", a.name));
        } else {
            out.push(vector(a, "cell"));
        }
    }
    if out.is_empty() {
        "none (pass --field distance)".into()
    } else {
        out.join(", ")
    }
}

fn choose<'m>(m: &'m ImportedMesh, scalar: Option<&str>) -> Result<Choice<'m>, CleanError> {
    let find = |name: &str| -> Option<Choice<'m>> {
        if let Some(a) = m.mesh.point_data.iter().find(|a| a.name == name) {
            return Some(Choice::Point(&a.name, &a.values, 1, None));
        }
        if let Some(a) = m.point_vectors.iter().find(|a| a.name == name) {
            return Some(Choice::Point(&a.name, &a.values, a.components, None));
        }
        m.cell_data
            .iter()
            .find(|a| a.name == name)
            .map(|a| Choice::Cell(a, None))
    };
    let Some(spec) = scalar else {
        let (i, _) = default_array(&arrays(m)).ok_or(CleanError::NoScalars)?;
        let np = m.mesh.point_data.len();
        let nv = m.point_vectors.len();
        return Ok(if i < np {
            let a = &m.mesh.point_data[i];
            Choice::Point(&a.name, &a.values, 1, None)
        } else if i < np + nv {
            let a = &m.point_vectors[i - np];
            Choice::Point(&a.name, &a.values, a.components, None)
        } else {
            Choice::Cell(&m.cell_data[i - np - nv], None)
        });
    };
    if let Some(c) = find(spec) {
        return Ok(c);
    }
    if let Some((name, comp)) = spec.rsplit_once(':') {
        if let Some(c) = find(name) {
            return Ok(match c {
                Choice::Point(n, v, nc, _) => {
                    Choice::Point(n, v, nc, parse_component(n, nc, comp)?)
                }
                Choice::Cell(a, _) => {
                    Choice::Cell(a, parse_component(&a.name, a.components, comp)?)
                }
            });
        }
    }
    Err(CleanError::UnknownScalar {
        name: spec.to_string(),
        available: available(m),
    })
}

/// Whether every non-NaN value is the same.
fn is_constant(values: impl IntoIterator<Item = f64>) -> bool {
    let mut first = None;
    for v in values.into_iter().filter(|v| !v.is_nan()) {
        match first {
            None => first = Some(v),
            Some(f) if f != v => return false,
            Some(_) => {}
        }
    }
    true
}

/// The mesh's arrays in the order the default choice tries them: point scalars, point vectors
/// (their magnitude), cell arrays (on the cells that gave tets).
pub fn arrays(m: &ImportedMesh) -> Vec<ArrayInfo> {
    let info = |name: &str, source: &str, components: usize, constant: bool| ArrayInfo {
        name: name.to_string(),
        source: source.to_string(),
        components,
        constant,
    };
    let mut out = Vec::new();
    for a in &m.mesh.point_data {
        out.push(info(
            &a.name,
            "point",
            1,
            is_constant(a.values.iter().copied()),
        ));
    }
    for a in &m.point_vectors {
        let mag = component(&a.values, a.components, None);
        out.push(info(&a.name, "point", a.components, is_constant(mag)));
    }
    for a in &m.cell_data {
        let v = component(&a.values, a.components, None);
        let on_tets = m.tet_cells.iter().filter_map(|&c| v.get(c).copied());
        out.push(info(&a.name, "cell", a.components, is_constant(on_tets)));
    }
    out
}

/// The array used without `--scalar`: the first that is not constant, else the first (with
/// `true`: every array is constant, the store will be blank). `None` without arrays.
pub fn default_array(arrays: &[ArrayInfo]) -> Option<(usize, bool)> {
    match arrays.iter().position(|a| !a.constant) {
        Some(i) => Some((i, false)),
        None if arrays.is_empty() => None,
        None => Some((0, true)),
    }
}

/// The report's name of a choice: `name`, `name:mag` or `name:K`.
fn choice_name(name: &str, nc: usize, c: Option<Component>) -> String {
    match (nc, c) {
        (1, _) => name.to_string(),
        (_, Some(Component::Index(k))) => format!("{name}:{k}"),
        _ => format!("{name}:mag"),
    }
}

/// Picks the scalar, checks for NaN/Inf, re-orients inverted tets, drops zero-volume and duplicate
/// ones, converts cell data to point data and measures the tets' quality.
pub fn clean_import(
    m: ImportedMesh,
    o: &ImportOptions<'_>,
) -> Result<(ScalarTetMesh, CleanReport), CleanError> {
    let c = m.counts;
    let mut report = CleanReport {
        points_read: m.mesh.points.len(),
        cells_read: c.cells_read,
        tets_read: m.mesh.tets.len(),
        cells_ignored: m.mesh.cells_ignored,
        cells_unsupported: c.cells_unsupported,
        cells_split: c.cells_split,
        cells_linearized: c.tets_linearized,
        ..Default::default()
    };
    if m.mesh.tets.is_empty() {
        return Err(CleanError::NoTets {
            ignored: c.cells_lower_dim,
            unsupported: match c.cells_unsupported {
                0 => String::new(),
                k => format!(", {k} volume cells of unsupported kinds"),
            },
        });
    }
    if let Some(index) = m
        .mesh
        .points
        .iter()
        .position(|p| p.iter().any(|x| !x.is_finite()))
    {
        return Err(CleanError::BadPoint { index });
    }
    if o.field.is_some() && o.scalar.is_some() {
        return Err(CleanError::FieldAndScalar);
    }
    if let Some(f) = o.field {
        if !f.eq_ignore_ascii_case("distance") {
            return Err(CleanError::UnknownField(f.to_string()));
        }
    }
    // a mesh with no arrays at all (geometry only) is drawn with the distance to its boundary,
    // as under --field distance, and the report says so
    let geometry_only = o.field.is_none() && o.scalar.is_none() && arrays(&m).is_empty();
    let choice = match o.field {
        _ if geometry_only => None,
        Some(_) => None,
        None => Some(choose(&m, o.scalar)?),
    };
    report.arrays = arrays(&m);
    let listed = || {
        report
            .arrays
            .iter()
            .map(|a| {
                let constant = if a.constant { ", constant" } else { "" };
                format!("{} ({}{constant})", a.name, a.source)
            })
            .collect::<Vec<_>>()
            .join(", ")
    };
    let mut default_notes = Vec::new();
    if choice.is_some() && o.scalar.is_none() {
        if let Some((i, all_constant)) = default_array(&report.arrays) {
            let name = &report.arrays[i].name;
            let list = listed();
            if all_constant {
                tracing::warn!(
                    array = %name,
                    arrays = %list,
                    "every array of the mesh is constant: the store will be blank"
                );
                default_notes.push(format!(
                    "warning: every array is constant ({list}): \"{name}\" is used and the store will be blank; pass --field distance to view the geometry"
                ));
            } else {
                tracing::info!(array = %name, arrays = %list, "scalar chosen by default");
                default_notes.push(format!(
                    "scalar \"{name}\" chosen by default (the first array that is not constant; --scalar NAME picks another); arrays: {list}"
                ));
            }
        }
    }

    // Geometry: orientation, zero-volume and duplicate tets.
    let points = &m.mesh.points;
    let (lo, hi) = bbox(points);
    let diag = ((hi[0] - lo[0]).powi(2) + (hi[1] - lo[1]).powi(2) + (hi[2] - lo[2]).powi(2)).sqrt();
    let eps = 1e-12 * diag.powi(3);
    let mut tets = Vec::with_capacity(m.mesh.tets.len());
    let mut cells = Vec::with_capacity(m.mesh.tets.len());
    let mut volumes = Vec::with_capacity(m.mesh.tets.len());
    let mut seen = HashSet::with_capacity(m.mesh.tets.len());
    for (t, &cell) in m.mesh.tets.iter().zip(&m.tet_cells) {
        let p = |k: usize| points[t[k] as usize];
        let v = signed_volume(p(0), p(1), p(2), p(3));
        if v.abs() <= eps {
            report.tets_dropped_degenerate += 1;
            continue;
        }
        let mut key = *t;
        key.sort_unstable();
        if !seen.insert(key) {
            report.tets_dropped_duplicate += 1;
            continue;
        }
        if v < 0.0 {
            tets.push([t[0], t[1], t[3], t[2]]);
            report.tets_reoriented += 1;
        } else {
            tets.push(*t);
        }
        cells.push(cell);
        volumes.push(v.abs());
    }
    report.tets_dropped = report.tets_dropped_degenerate + report.tets_dropped_duplicate;
    if tets.is_empty() {
        return Err(CleanError::AllDegenerate {
            count: m.mesh.tets.len(),
        });
    }
    report.tets_kept = tets.len();

    // The scalar.
    let n = points.len();
    let distance = choice.is_none();
    let mut values = match choice {
        None => {
            report.scalar = "distance".into();
            report.scalar_source = "geometric".into();
            report.notes.push(if geometry_only {
                tracing::info!("the mesh has no arrays: drawn with the distance to its boundary");
                "the mesh has no point or cell arrays: its scalar is the distance to its boundary (as --field distance)".into()
            } else {
                "scalar: the distance to the mesh's boundary (--field distance)".into()
            });
            boundary_distance(points, &tets)
        }
        Some(Choice::Point(name, v, nc, comp)) => {
            report.scalar = choice_name(name, nc, comp);
            report.scalar_source = "point".into();
            if nc > 1 && comp.is_none() {
                report.notes.push(format!(
                    "point array \"{name}\" has {nc} components: its magnitude is used"
                ));
            }
            component(v, nc, comp)
        }
        Some(Choice::Cell(a, comp)) => {
            report.scalar = choice_name(&a.name, a.components, comp);
            report.scalar_source = "cell".into();
            let per_cell = component(&a.values, a.components, comp);
            report.notes.push(format!(
                "cell array \"{}\" converted to point data by volume-weighted averaging over the tets around each point",
                report.scalar
            ));
            let mut num = vec![0.0; n];
            let mut den = vec![0.0; n];
            for ((t, &cell), &vol) in tets.iter().zip(&cells).zip(&volumes) {
                let x = per_cell.get(cell).copied().unwrap_or(f64::NAN);
                for &v in t {
                    num[v as usize] += vol * x;
                    den[v as usize] += vol;
                }
            }
            num.iter()
                .zip(&den)
                .map(|(&a, &d)| if d > 0.0 { a / d } else { 0.0 })
                .collect()
        }
    };
    report.notes.extend(default_notes);
    let bad: Vec<usize> = values
        .iter()
        .enumerate()
        .filter(|(_, v)| !v.is_finite())
        .map(|(i, _)| i)
        .collect();
    if !bad.is_empty() {
        match o.nan_as {
            Some(x) => {
                for &i in &bad {
                    values[i] = x;
                }
                report.non_finite_replaced = bad.len();
            }
            None => {
                return Err(CleanError::NonFinite {
                    name: report.scalar.clone(),
                    count: bad.len(),
                    first: bad[0],
                })
            }
        }
    }

    // Quality.
    report.min_dihedral_deg = 180.0;
    for t in &tets {
        let a = min_dihedral_deg(t.map(|v| points[v as usize]));
        report.min_dihedral_deg = report.min_dihedral_deg.min(a);
        if a < SLIVER_DEGREES {
            report.slivers += 1;
        }
    }

    // Notes.
    if c.tets_linearized > 0 {
        report.notes.push(format!(
            "{} higher-order tets reduced to their corner tets",
            c.tets_linearized
        ));
    }
    if c.cells_split > 0 {
        report.notes.push(format!(
            "{} hexahedra, wedges and pyramids split into {} tets (quad faces cut from their smallest point index)",
            c.cells_split, c.tets_from_split
        ));
    }
    if c.cells_lower_dim > 0 {
        report.notes.push(format!(
            "{} points, lines and surface cells ignored",
            c.cells_lower_dim
        ));
    }
    if c.cells_unsupported > 0 {
        report.notes.push(format!(
            "{} volume cells of unsupported kinds (polyhedra, Lagrange cells...) ignored",
            c.cells_unsupported
        ));
    }
    if report.tets_reoriented > 0 {
        report.notes.push(format!(
            "{} inverted tets re-oriented",
            report.tets_reoriented
        ));
    }
    if report.tets_dropped > 0 {
        report.notes.push(format!(
            "{} tets dropped ({} zero-volume, {} duplicate)",
            report.tets_dropped, report.tets_dropped_degenerate, report.tets_dropped_duplicate
        ));
    }
    report.notes.push(format!(
        "quality: min dihedral angle {:.2} degrees, {} slivers (below {SLIVER_DEGREES} degrees)",
        report.min_dihedral_deg, report.slivers
    ));
    Ok((
        ScalarTetMesh {
            points: m.mesh.points,
            tets,
            values,
            distance,
        },
        report,
    ))
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// The smallest of a tet's six dihedral angles, in degrees.
pub fn min_dihedral_deg(p: [[f64; 3]; 4]) -> f64 {
    // Outward normal of the face opposite each vertex.
    let normals = [0, 1, 2, 3].map(|i| {
        let f: Vec<[f64; 3]> = (0..4).filter(|&k| k != i).map(|k| p[k]).collect();
        let n = cross(sub(f[1], f[0]), sub(f[2], f[0]));
        if dot(n, sub(p[i], f[0])) > 0.0 {
            n.map(|x| -x)
        } else {
            n
        }
    });
    let mut best = 180.0f64;
    for i in 0..4 {
        for j in i + 1..4 {
            let (a, b) = (normals[i], normals[j]);
            let c = dot(a, b) / (dot(a, a) * dot(b, b)).sqrt();
            let angle = 180.0 - c.clamp(-1.0, 1.0).acos().to_degrees();
            best = best.min(angle);
        }
    }
    best
}

/// Distance from every point to the boundary surface of the tets (the faces that only one tet
/// has); 0 at the points on it. See [`BoundaryDistance`].
pub fn boundary_distance(points: &[[f64; 3]], tets: &[[u32; 4]]) -> Vec<f64> {
    let d = BoundaryDistance::new(points, tets);
    if d.tris.is_empty() {
        return vec![0.0; points.len()];
    }
    let mut on_boundary = vec![false; points.len()];
    for f in &d.faces {
        for &v in f {
            on_boundary[v as usize] = true;
        }
    }
    points
        .iter()
        .zip(&on_boundary)
        .map(|(&p, &on)| if on { 0.0 } else { d.distance(p) })
        .collect()
}

/// The boundary surface of a tet mesh (the faces that only one tet has) in a bounding volume
/// hierarchy (boxes split at the median of the triangles' centroids along their longest axis, at
/// most 4 triangles a leaf), for the distance from any point to it: nearer boxes first, a box no
/// nearer than the best triangle so far is skipped. A query costs about `log n` boxes wherever
/// the point is, deep inside the mesh or next to its surface.
pub struct BoundaryDistance {
    faces: Vec<[u32; 3]>,
    tris: Vec<[[f64; 3]; 3]>,
    nodes: Vec<BvhNode>,
}

/// A box of the hierarchy: a leaf holds `tris[start..start + count]`, an inner node (`count` 0)
/// has its children at `start` and `start + 1`.
struct BvhNode {
    lo: [f64; 3],
    hi: [f64; 3],
    start: u32,
    count: u32,
}

const BVH_LEAF: usize = 4;

impl BoundaryDistance {
    pub fn new(points: &[[f64; 3]], tets: &[[u32; 4]]) -> Self {
        let mut faces: HashMap<[u32; 3], u32> = HashMap::with_capacity(tets.len() * 2);
        for t in tets {
            for skip in 0..4 {
                let mut f = [0u32; 3];
                let mut k = 0;
                for (i, &v) in t.iter().enumerate() {
                    if i != skip {
                        f[k] = v;
                        k += 1;
                    }
                }
                f.sort_unstable();
                *faces.entry(f).or_default() += 1;
            }
        }
        let mut boundary: Vec<[u32; 3]> = faces
            .into_iter()
            .filter(|&(_, c)| c == 1)
            .map(|(f, _)| f)
            .collect();
        boundary.sort_unstable();
        let mut tris: Vec<[[f64; 3]; 3]> = boundary
            .iter()
            .map(|f| f.map(|v| points[v as usize]))
            .collect();
        let mut nodes = Vec::with_capacity(2 * tris.len() / BVH_LEAF + 1);
        if !tris.is_empty() {
            nodes.push(BvhNode {
                lo: [0.0; 3],
                hi: [0.0; 3],
                start: 0,
                count: 0,
            });
            // (node, range of tris): the range is sorted in place, children appended in pairs.
            let mut todo = vec![(0usize, 0usize, tris.len())];
            while let Some((node, a, b)) = todo.pop() {
                let (lo, hi) = bbox(tris[a..b].iter().flatten());
                nodes[node].lo = lo;
                nodes[node].hi = hi;
                if b - a <= BVH_LEAF {
                    nodes[node].start = a as u32;
                    nodes[node].count = (b - a) as u32;
                    continue;
                }
                let centroid = |t: &[[f64; 3]; 3], k: usize| t[0][k] + t[1][k] + t[2][k];
                let (clo, chi) = bbox(
                    tris[a..b]
                        .iter()
                        .map(|t| [0, 1, 2].map(|k| centroid(t, k)))
                        .collect::<Vec<_>>()
                        .iter(),
                );
                let axis = (0..3)
                    .max_by(|&x, &y| (chi[x] - clo[x]).total_cmp(&(chi[y] - clo[y])))
                    .unwrap_or(0);
                let mid = (b - a) / 2;
                tris[a..b].select_nth_unstable_by(mid, |s, t| {
                    centroid(s, axis).total_cmp(&centroid(t, axis))
                });
                let child = nodes.len();
                for _ in 0..2 {
                    nodes.push(BvhNode {
                        lo: [0.0; 3],
                        hi: [0.0; 3],
                        start: 0,
                        count: 0,
                    });
                }
                nodes[node].start = child as u32;
                todo.push((child, a, a + mid));
                todo.push((child + 1, a + mid, b));
            }
        }
        BoundaryDistance {
            faces: boundary,
            tris,
            nodes,
        }
    }

    /// Distance from `p` to the boundary surface (infinite if the mesh has none).
    pub fn distance(&self, p: [f64; 3]) -> f64 {
        self.distance_within(p, f64::INFINITY)
    }

    /// `min(distance(p), cap)`: boxes farther than `cap` are never opened, so a point far from
    /// the surface with a small cap costs a few box tests.
    pub fn distance_within(&self, p: [f64; 3], cap: f64) -> f64 {
        let box_d2 = |n: &BvhNode| {
            (0..3)
                .map(|k| {
                    let d = (n.lo[k] - p[k]).max(p[k] - n.hi[k]).max(0.0);
                    d * d
                })
                .sum::<f64>()
        };
        let mut best = cap;
        let mut best2 = cap * cap;
        let mut stack: Vec<(u32, f64)> = Vec::with_capacity(64);
        if let Some(root) = self.nodes.first() {
            stack.push((0, box_d2(root)));
        }
        while let Some((ni, d2)) = stack.pop() {
            if d2 >= best2 {
                continue;
            }
            let n = &self.nodes[ni as usize];
            if n.count > 0 {
                let (a, b) = (n.start as usize, (n.start + n.count) as usize);
                for q in &self.tris[a..b] {
                    best = best.min(point_triangle_distance(p, q[0], q[1], q[2]));
                }
                best2 = best * best;
                continue;
            }
            let (l, r) = (n.start, n.start + 1);
            let dl = box_d2(&self.nodes[l as usize]);
            let dr = box_d2(&self.nodes[r as usize]);
            // The nearer child is popped first.
            if dl <= dr {
                stack.push((r, dr));
                stack.push((l, dl));
            } else {
                stack.push((l, dl));
                stack.push((r, dr));
            }
        }
        best
    }
}

/// Distance from `p` to the triangle `abc` (Ericson, Real-Time Collision Detection, 5.1.5).
fn point_triangle_distance(p: [f64; 3], a: [f64; 3], b: [f64; 3], c: [f64; 3]) -> f64 {
    let ab = sub(b, a);
    let ac = sub(c, a);
    let ap = sub(p, a);
    let d1 = dot(ab, ap);
    let d2 = dot(ac, ap);
    let dist = |q: [f64; 3]| dot(sub(p, q), sub(p, q)).sqrt();
    let along =
        |o: [f64; 3], d: [f64; 3], t: f64| [o[0] + t * d[0], o[1] + t * d[1], o[2] + t * d[2]];
    if d1 <= 0.0 && d2 <= 0.0 {
        return dist(a);
    }
    let bp = sub(p, b);
    let d3 = dot(ab, bp);
    let d4 = dot(ac, bp);
    if d3 >= 0.0 && d4 <= d3 {
        return dist(b);
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        return dist(along(a, ab, d1 / (d1 - d3)));
    }
    let cp = sub(p, c);
    let d5 = dot(ab, cp);
    let d6 = dot(ac, cp);
    if d6 >= 0.0 && d5 <= d6 {
        return dist(c);
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        return dist(along(a, ac, d2 / (d2 - d6)));
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        return dist(along(b, sub(c, b), (d4 - d3) / ((d4 - d3) + (d5 - d6))));
    }
    let denom = 1.0 / (va + vb + vc);
    let v = vb * denom;
    let w = vc * denom;
    dist([
        a[0] + ab[0] * v + ac[0] * w,
        a[1] + ab[1] * v + ac[1] * w,
        a[2] + ab[2] * v + ac[2] * w,
    ])
}

pub fn bbox<'p>(points: impl IntoIterator<Item = &'p [f64; 3]>) -> ([f64; 3], [f64; 3]) {
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for p in points {
        for a in 0..3 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    }
    (lo, hi)
}

#[cfg(test)]
mod tests {

    /// `:mag` is the Frobenius norm: of a 6-component symmetric tensor (off-diagonal terms twice),
    /// of a 9-component full tensor, and the Euclidean norm of a vector.
    #[test]
    fn magnitude_is_the_frobenius_norm_of_tensors() {
        let sym = [1.0, 2.0, 3.0, 4.0, 5.0, 6.0];
        let full = [1.0, 4.0, 6.0, 4.0, 2.0, 5.0, 6.0, 5.0, 3.0];
        let m = Some(Component::Magnitude);
        let want = (1.0f64 + 4.0 + 9.0 + 2.0 * (16.0 + 25.0 + 36.0)).sqrt();
        assert_eq!(component(&sym, 6, m), vec![want]);
        assert!((component(&full, 9, m)[0] - want).abs() < 1e-12);
        assert_eq!(component(&[3.0, 4.0, 0.0], 3, m), vec![5.0]);
    }

    use super::*;

    /// The hierarchy finds the same nearest triangle as a look at every one, for points inside,
    /// on and outside a surface of 768 triangles.
    #[test]
    fn boundary_distance_matches_brute_force() {
        let (mut points, mut tets) = (Vec::new(), Vec::new());
        for c in 0..64u32 {
            let o = [
                f64::from(c % 4),
                f64::from(c / 4 % 4),
                f64::from(c / 16) * 0.7,
            ];
            let (p, t) = tetwave_protocol::shapes::box6(o, [o[0] + 1.0, o[1] + 0.9, o[2] + 0.5]);
            let base = points.len() as u32;
            points.extend(p);
            tets.extend(t.iter().map(|t| t.map(|v| v + base)));
        }
        let d = BoundaryDistance::new(&points, &tets);
        assert_eq!(d.tris.len(), 64 * 12);
        let mut x = 0x2545_f491_4f6c_dd1du64;
        let mut next = || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            (x >> 11) as f64 / (1u64 << 53) as f64
        };
        for _ in 0..2000 {
            let p = [next() * 6.0 - 1.0, next() * 6.0 - 1.0, next() * 4.0 - 1.0];
            let brute = d
                .tris
                .iter()
                .map(|q| point_triangle_distance(p, q[0], q[1], q[2]))
                .fold(f64::INFINITY, f64::min);
            assert_eq!(d.distance(p), brute, "at {p:?}");
        }
        assert_eq!(d.distance(points[5]), 0.0);
    }
}
