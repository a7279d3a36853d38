//! Resampling: builds the semi-regular mesh (a base mesh refined `L` times by Bey) over a volume and
//! samples the scalar at every vertex of the finest level.
//!
//! Inputs: an analytic field ([`synthetic`]), a raw grid ([`raw`], trilinear) or an unstructured tet
//! mesh (read by [`tetwave_import`]; [`unstructured`] location and barycentric interpolation).
//!
//! **Outside rule.** A vertex where the input has no data (outside a non-convex mesh) is marked outside
//! (`NaN` in [`Resampled::samples`]). Analysis gives it a zero detail, i.e. the linear prediction from
//! its coarser neighbours (base vertices outside take the mean of the inside samples), so it carries no
//! information of its own; a tet whose every finest-level vertex is outside is *empty*: flagged in its
//! parent's node (or the base mesh), never refined by the client and never drawn.

pub mod base;
pub mod levelset;
pub mod raw;
pub mod synthetic;
pub mod unstructured;

use rayon::prelude::*;
use std::path::PathBuf;
use tetwave_import as import;
use tetwave_protocol::hierarchy::MAX_LEVELS;
use tetwave_protocol::vertex::VertexKeys;
use tetwave_protocol::{BaseMesh, Forest};

/// Detail nodes a hierarchy may have: the analysis codes a vertex's owner as 8 × node id + edge,
/// in a u64 past 2^29 nodes (below `u64::MAX`, its "no owner"). [`resample`] refuses more before
/// it allocates the samples, and the analysis checks it again; memory binds long before.
pub const MAX_NODES: u64 = u64::MAX >> 3;

/// Where the scalar comes from.
pub enum Source {
    Synthetic(synthetic::Synthetic),
    Raw(raw::RawGrid),
    Mesh(Box<unstructured::Locator>, ([f64; 3], [f64; 3])),
}

impl Source {
    pub fn bounds(&self) -> ([f64; 3], [f64; 3]) {
        match self {
            Source::Synthetic(s) => s.bounds(),
            Source::Raw(g) => g.bounds(),
            Source::Mesh(_, b) => *b,
        }
    }

    /// The scalar at `p`, `None` where the input has no data.
    pub fn sample(&self, p: [f64; 3]) -> Option<f64> {
        match self {
            Source::Synthetic(s) => Some(s.eval(p)),
            Source::Raw(g) => Some(g.sample(p)),
            Source::Mesh(l, _) => l.sample(p),
        }
    }
}

/// The coarse mesh the hierarchy refines.
#[derive(Debug, Clone, PartialEq)]
pub enum BaseSpec {
    /// What suits the input (`prepare`'s default): for a raw grid, the Kuhn boxes that make every
    /// voxel a vertex ([`raw::VoxelLattice`]); for anything else, [`BaseSpec::Box5`].
    Auto,
    /// The bounding box split into 5 tets (thesis).
    Box5,
    /// The bounding box split into 6 Kuhn tets.
    Box6,
    /// The box `[lo, hi]` cut into `cells` equal Kuhn cells ([`tetwave_protocol::shapes::kuhn_boxes`]):
    /// what [`BaseSpec::Auto`] means for a raw grid. Not the input's bounds: it may reach past
    /// them (padding).
    KuhnBoxes {
        lo: [f64; 3],
        hi: [f64; 3],
        cells: [usize; 3],
    },
    /// A coarse conforming tet mesh file (.vtu/.vtk/.msh).
    File(PathBuf),
}

impl BaseSpec {
    /// The name a store's manifest records (one Kuhn box is `box6`, which streams as a name).
    pub fn name(&self) -> String {
        match self {
            BaseSpec::Auto | BaseSpec::Box5 => "box5".into(),
            BaseSpec::Box6
            | BaseSpec::KuhnBoxes {
                cells: [1, 1, 1], ..
            } => "box6".into(),
            BaseSpec::KuhnBoxes {
                cells: [x, y, z], ..
            } => format!("kuhn-boxes {x}x{y}x{z}"),
            BaseSpec::File(p) => p.display().to_string(),
        }
    }
}

impl std::str::FromStr for BaseSpec {
    type Err = std::convert::Infallible;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Ok(match s {
            "auto" => BaseSpec::Auto,
            "box5" => BaseSpec::Box5,
            "box6" => BaseSpec::Box6,
            other => BaseSpec::File(PathBuf::from(other)),
        })
    }
}

#[derive(Debug, thiserror::Error)]
pub enum ResampleError {
    #[error("--levels {0} is beyond the supported {MAX_LEVELS}")]
    TooManyLevels(u8),
    #[error("the input's bounding box is degenerate: {lo:?} .. {hi:?}")]
    DegenerateBounds { lo: [f64; 3], hi: [f64; 3] },
    #[error("base mesh: {0}")]
    BaseFile(#[from] import::ImportError),
    #[error("base mesh: {0}")]
    BaseInvalid(String),
    #[error(
        "no vertex of the semi-regular mesh falls inside the input's domain at {0} levels: its \
         lattice is too coarse for this mesh; raise --levels"
    )]
    NothingInside(u8),
    #[error("sampled value {value} at {pos:?} does not fit in f32")]
    OutOfRange { value: f64, pos: [f64; 3] },
    #[error("the finest level has {0} vertices; that is more than this build can index")]
    TooLarge(u64),
    #[error(
        "--levels {levels}: {tets} tets in the finest level is more than the analysis can index; \
         this base mesh takes at most --levels {most}"
    )]
    TooManyNodes { levels: u8, tets: u64, most: u8 },
    #[error("cannot allocate {bytes} bytes for the samples of {vertices} vertices")]
    NoMemory { vertices: u64, bytes: u64 },
}

/// The semi-regular mesh's samples.
#[derive(Clone)]
pub struct Resampled {
    /// Base mesh; `values` holds the samples at its vertices (outside ones filled by analysis) and
    /// `empty` is filled by analysis.
    pub base: BaseMesh,
    pub keys: VertexKeys,
    /// One sample per vertex key; `NaN` marks a vertex outside the input's domain.
    pub samples: Vec<f32>,
    pub outside: u64,
}

/// Whether a hierarchy of `levels` levels over `tets` base tets can be indexed (at most
/// [`MAX_NODES`] nodes).
pub fn indexable(tets: u64, levels: u8) -> bool {
    Forest::new(tets, levels)
        .checked_nodes()
        .is_some_and(|n| n <= MAX_NODES)
}

/// Builds the base mesh.
pub fn base_mesh(
    spec: &BaseSpec,
    bounds: ([f64; 3], [f64; 3]),
) -> Result<base::PointsAndTets, ResampleError> {
    let (lo, hi) = match spec {
        BaseSpec::KuhnBoxes { lo, hi, .. } => (*lo, *hi),
        _ => bounds,
    };
    if !matches!(spec, BaseSpec::File(_))
        && (0..3).any(|a| hi[a] <= lo[a] || !(hi[a] - lo[a]).is_finite())
    {
        return Err(ResampleError::DegenerateBounds { lo, hi });
    }
    match spec {
        BaseSpec::Auto | BaseSpec::Box5 => Ok(base::box5(lo, hi)),
        BaseSpec::Box6 => Ok(base::box6(lo, hi)),
        BaseSpec::KuhnBoxes { cells, .. } => Ok(base::kuhn_boxes(lo, hi, *cells)),
        BaseSpec::File(path) => {
            let mesh = import::read_tet_mesh(path)?;
            if mesh.tets.is_empty() {
                return Err(ResampleError::BaseInvalid(format!(
                    "{}: no tetrahedra",
                    path.display()
                )));
            }
            let points = mesh.points;
            let mut tets = mesh.tets;
            for t in &tets {
                let p = |k: usize| points[t[k] as usize];
                if tetwave_protocol::base::signed_volume(p(0), p(1), p(2), p(3)).abs() == 0.0 {
                    return Err(ResampleError::BaseInvalid(format!(
                        "{}: a base tet has zero volume",
                        path.display()
                    )));
                }
            }
            let flipped = base::orient_positive(&points, &mut tets);
            if flipped > 0 {
                tracing::warn!(flipped, "base mesh: re-oriented inverted tets");
            }
            Ok((points, tets))
        }
    }
}

/// Samples `source` at every vertex of the base mesh refined `levels` times.
pub fn resample(source: &Source, spec: &BaseSpec, levels: u8) -> Result<Resampled, ResampleError> {
    if levels > MAX_LEVELS {
        return Err(ResampleError::TooManyLevels(levels));
    }
    let (positions, tets) = base_mesh(spec, source.bounds())?;
    resample_onto(source, (positions, tets), levels)
}

/// Samples `source` at every vertex of the base mesh `(positions, tets)` refined `levels` times:
/// [`resample`] on a base mesh already built (`verify --input` samples the input again on a
/// store's own base mesh, as `prepare` did).
pub fn resample_onto(
    source: &Source,
    (positions, tets): base::PointsAndTets,
    levels: u8,
) -> Result<Resampled, ResampleError> {
    if levels > MAX_LEVELS {
        return Err(ResampleError::TooManyLevels(levels));
    }
    let mut base = BaseMesh {
        levels,
        positions,
        tets,
        values: Vec::new(),
        empty: Vec::new(),
        predictor: Default::default(),
    };
    let forest = base.forest();
    let fits = |l: u8| indexable(forest.n_base, l);
    if levels > 0 && !fits(levels) {
        let most = (0..levels).rev().find(|&l| fits(l)).unwrap_or(0);
        return Err(ResampleError::TooManyNodes {
            levels,
            tets: forest.level_len(levels),
            most,
        });
    }
    let keys = base.vertex_keys();
    let n = keys.vertex_count();
    if n > (usize::MAX / 8) as u64 || n > u32::MAX as u64 * 4 {
        return Err(ResampleError::TooLarge(n));
    }
    let mut samples = Vec::new();
    samples
        .try_reserve_exact(n as usize)
        .map_err(|_| ResampleError::NoMemory {
            vertices: n,
            bytes: n * 4,
        })?;
    samples.resize(n as usize, f32::NAN);
    // split the sample array into the entities' contiguous key ranges and fill them in parallel
    let entities = keys.entities();
    let mut chunks: Vec<(tetwave_protocol::vertex::Entity, u64, &mut [f32])> =
        Vec::with_capacity(entities.len());
    let mut rest: &mut [f32] = &mut samples;
    let mut at = 0u64;
    for (e, r) in &entities {
        let skip = (r.start - at) as usize;
        let (_, tail) = rest.split_at_mut(skip);
        let (mine, tail) = tail.split_at_mut((r.end - r.start) as usize);
        chunks.push((*e, r.start, mine));
        rest = tail;
        at = r.end;
    }
    let failure = std::sync::Mutex::new(None);
    chunks.into_par_iter().for_each(|(entity, start, out)| {
        keys.for_each_in(entity, |key, tet, w| {
            let p = base.position(tet, &w);
            if let Some(v) = source.sample(p) {
                let f = v as f32;
                if !f.is_finite() {
                    *failure.lock().unwrap() = Some(ResampleError::OutOfRange { value: v, pos: p });
                }
                out[(key - start) as usize] = f;
            }
        });
    });
    if let Some(e) = failure.into_inner().unwrap() {
        return Err(e);
    }
    let outside = samples.iter().filter(|x| x.is_nan()).count() as u64;
    if outside == n {
        return Err(ResampleError::NothingInside(levels));
    }
    base.values = samples[..base.positions.len()].to_vec();
    Ok(Resampled {
        base,
        keys,
        samples,
        outside,
    })
}
