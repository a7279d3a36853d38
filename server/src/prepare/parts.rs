//! Preparing a raw grid's store by parts (`prepare --parts N --part K`, then `prepare --parts N
//! --finish`): each part reads a slab of the grid, analyses it alone and writes its nodes; the
//! finish writes the store from the parts' files, equal byte for byte to the one-process store
//! of the same options (docs/scale.md).
//!
//! **Why a slab analyses alone.** A raw grid's base mesh is a box of Kuhn cells, numbered x
//! fastest, z slowest, 6 tets a cell; a part takes whole layers of cells along z, so its base
//! tets are one id range `[b0, b1)`, and at every level its nodes are the ids
//! `level_start(l) + [b0·8^l, b1·8^l)`: one range a level, in the same order as in the whole. The
//! analysis of the layers alone differs from the whole's only on the plane a part shares with the
//! part below: a new vertex there is predicted from values on that plane alone (a linear
//! prediction on a base edge, the parent's quadratic restricted to the face it lies in), so both
//! parts compute the same detail, and the contract gives it to the lowest-id tet around its edge,
//! which is the lower part's. A part above the first drops the details it owns on its lower plane
//! and leaves those vertices out of its histogram; the quantizer and the bound follow from the
//! whole grid's value range, which every part reads first (one pass over the file, by slabs).
//!
//! **Files.** Part `K` of `N` writes `parts/part-K-of-N/nodes.bin` (its nodes in id order, coded
//! as a store codes them, in blocks of up to 4,096 ids of one level, each a bincode [`NodeBlock`]) and then `parts/part-K-of-N/part.json` ([`PartSummary`]); no file is
//! written by two parts, and a part without its summary is not done. The finish reads the
//! summaries (refusing any missing, naming them), codes the blocks as the nodes stream in,
//! writes the manifest last and removes `parts/`.

use super::{GridArgs, PrepareError, PrepareOptions, Summary, PREPARE_BYTES_PER_VERTEX};
use crate::analysis::{analyze_hierarchy_in_range, ErrorBound, Precision};
use crate::resample::raw::{VoxelLattice, MOST_AUTO_CELLS, MOST_BASE_TETS};
use crate::resample::{base_mesh, indexable, resample, BaseSpec, Source};
use serde::{Deserialize, Serialize};
use std::collections::VecDeque;
use std::io::{BufReader, BufWriter, Write};
use std::path::{Path, PathBuf};
use std::time::Instant;
use tetwave_protocol::block::{BlockCoder, NodeBlock};
use tetwave_protocol::hierarchy::{LevelWalker, EDGES};
use tetwave_protocol::levelset::NearLevelSet;
use tetwave_protocol::store_format::Encoding;
use tetwave_protocol::wavelet::{LevelSteps, Predictor, Quantizer};
use tetwave_protocol::{BaseMesh, DetailNode, Forest};
use tetwave_store::{self as store, StoreError, StoreMeta, Totals};

/// `prepare --parts N --part K | --finish`.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct PartsArgs {
    /// Prepare a raw grid's store in N parts, each of which can run on its own machine (a Slurm
    /// array task, a Kubernetes indexed job): `--part K` (0-based) writes part K under
    /// `OUT/parts/`, and `--finish` writes the store from all N once they are done. The store
    /// equals the one-process store of the same options. The grid's lattice needs at least N
    /// layers of boxes along z (fewer --levels give more).
    #[arg(long)]
    pub parts: Option<u32>,
    /// The part to prepare (0-based, with --parts).
    #[arg(long, requires = "parts", conflicts_with = "finish")]
    pub part: Option<u32>,
    /// Write the store from the N parts' files (with --parts; the same options as the parts).
    #[arg(long, requires = "parts")]
    pub finish: bool,
}

/// What a part writes last (`part.json`): what the finish needs of it besides its nodes.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct PartSummary {
    pub format: String,
    pub parts: u32,
    pub part: u32,
    /// The options every part and the finish must share ([`Fingerprint`]).
    pub options: Fingerprint,
    /// The part's base tets, `[b0, b1)`.
    pub base_tets: [u64; 2],
    /// Per node level, the ids of the part's nodes: `[start, end)`.
    pub node_ranges: Vec<[u64; 2]>,
    pub coefficients: u64,
    /// `nodes.bin`'s size and CRC-32.
    pub nodes_bytes: u64,
    pub nodes_crc32: u32,
    pub value_range: [f32; 2],
    pub max_abs_error: f64,
    pub error_bound: f64,
    pub quantizer: Option<Quantizer>,
    pub histogram: Vec<u64>,
    /// The reconstructed values of the part's base vertices, by the whole base mesh's index.
    pub base_values: Vec<(u64, f32)>,
    /// The part's empty base tets, by the whole base mesh's index.
    pub empty_base_tets: Vec<u64>,
    pub seconds: f64,
}

/// The options that make a store: a part prepared with others than its siblings' is refused.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Fingerprint {
    pub input_bytes: u64,
    pub dims: [usize; 3],
    pub dtype: String,
    pub spacing: [f64; 3],
    pub levels: u8,
    pub cells: [usize; 3],
    /// `None`: lossless; else the `--max-error` bound as given.
    pub max_error: Option<String>,
    pub nan_as: Option<f64>,
}

const PART_FORMAT: &str = "tetwave-store-part";
pub(super) const NODES_FILE: &str = "nodes.bin";
pub(super) const SUMMARY_FILE: &str = "part.json";

/// Part `k` of `n`'s folder under the store: `parts/part-K-of-N`.
pub(super) fn part_rel(n: u32, k: u32) -> String {
    format!("parts/part-{k}-of-{n}")
}

fn part_dir(out: &Path, n: u32, k: u32) -> PathBuf {
    out.join(part_rel(n, k))
}

/// The grid, its lattice and the layers of boxes each part takes.
struct Plan {
    grid: GridArgs,
    path: PathBuf,
    dims: [usize; 3],
    lattice: VoxelLattice,
    fingerprint: Fingerprint,
    precision: Precision,
    n: u32,
    /// 1: a part is whole layers; `m > 1`: a part is one layer's `1/m` of its rows of boxes.
    rows_split: usize,
}

/// The boxes a part takes: rows (along y) and layers (along z) of the lattice's boxes, all of
/// them along x.
#[derive(Debug, Clone)]
struct PartBox {
    rows: std::ops::Range<usize>,
    layers: std::ops::Range<usize>,
}

impl Plan {
    fn new(o: &PrepareOptions, n: u32) -> Result<Self, PrepareError> {
        let usage = |s: &str| Err(PrepareError::Usage(s.into()));
        if n == 0 {
            return usage("--parts must be at least 1");
        }
        // a volume file's header gives its dims (as `prepare` reads it, once per part)
        let grid = match o.read.resolve_volume(&o.input)? {
            Some(read) => read.grid,
            None => o.read.grid.clone(),
        };
        let Some(dims) = grid.dims else {
            return usage(
                "--parts prepares a grid (a volume file, or a raw grid with --dims and --dtype); \
                 meshes and synthetic fields are prepared in one process",
            );
        };
        if !matches!(o.base, BaseSpec::Auto) {
            return usage("--parts keeps every voxel: leave --base at auto");
        }
        if o.preview.is_some() || o.keep_reference {
            return usage("--parts writes no --preview and no --keep-reference");
        }
        if o.predictor == super::PredictorChoice::Axes {
            return usage(
                "--parts analyses with the parent predictor (--predictor axes needs one box)",
            );
        }
        let precision =
            match (o.bits, o.max_error) {
                (None, None) => Precision::Lossless,
                (None, Some(e)) => Precision::MaxError(e),
                (Some(_), _) => return usage(
                    "--parts takes a lossless store or --max-error: --bits sizes its step from \
                     every detail of the whole",
                ),
            };
        let path = PathBuf::from(&o.input);
        let input_bytes = if tetwave_import::volume::is_url(&path) {
            0
        } else {
            std::fs::metadata(&path)
                .map_err(|source| crate::resample::raw::RawError::Io {
                    path: path.clone(),
                    source,
                })?
                .len()
        };
        let lattice = VoxelLattice::fit(dims, grid.spacing, o.levels, indexable)?;
        let [_, rows, layers] = lattice.cells;
        let n_ = n as usize;
        let rows_split = if n_ <= layers {
            1
        } else if n_.is_multiple_of(layers) && n_ / layers <= rows {
            n_ / layers
        } else {
            return Err(PrepareError::Usage(format!(
                "--parts {n}: the voxel lattice has {layers} layer(s) of {rows} row(s) of boxes \
                 at {} levels; give at most {layers} parts (whole layers), or a multiple of \
                 {layers} up to {} (rows of each layer), or fewer --levels (each level fewer \
                 doubles the layers and the rows)",
                lattice.levels,
                layers * rows
            )));
        };
        let fingerprint = Fingerprint {
            input_bytes,
            dims,
            dtype: grid.dtype.clone(),
            spacing: grid.spacing,
            levels: lattice.levels,
            cells: lattice.cells,
            max_error: o.max_error.map(|e| match e {
                ErrorBound::Absolute(e) => format!("{e:e}"),
                ErrorBound::OfRange(f) => format!("{:e}%", f * 100.0),
            }),
            nan_as: o.read.nan_as,
        };
        Ok(Plan {
            grid,
            path,
            dims,
            lattice,
            fingerprint,
            precision,
            n,
            rows_split,
        })
    }

    /// The boxes of part `k`.
    fn part_box(&self, k: u32) -> PartBox {
        let [_, cy, cz] = self.lattice.cells;
        let k = k as usize;
        match self.rows_split {
            1 => {
                let n = self.n as usize;
                PartBox {
                    rows: 0..cy,
                    layers: k * cz / n..(k + 1) * cz / n,
                }
            }
            m => {
                let (layer, r) = (k / m, k % m);
                PartBox {
                    rows: r * cy / m..(r + 1) * cy / m,
                    layers: layer..layer + 1,
                }
            }
        }
    }

    /// The whole grid's value range, read slab by slab (NaN/Inf as `nan_as` says).
    fn value_range(&self, nan_as: Option<f64>) -> Result<(f32, f32), PrepareError> {
        let plane = self.dims[0] * self.dims[1];
        let slab = (64usize << 20).div_ceil(plane).max(1);
        let mut range: Option<(f32, f32)> = None;
        for z0 in (0..self.dims[2]).step_by(slab) {
            let z1 = (z0 + slab).min(self.dims[2]);
            let g = self.grid.read_slab(&self.path, nan_as, z0..z1)?;
            if let Some((lo, hi)) = g.value_range() {
                range = Some(range.map_or((lo, hi), |(a, b)| (a.min(lo), b.max(hi))));
            }
        }
        range.ok_or_else(|| {
            PrepareError::Usage(format!("{}: no finite sample", self.path.display()))
        })
    }

    /// The whole store's base mesh, its values NaN and no tet empty (the parts give them).
    fn whole_base(&self) -> Result<BaseMesh, PrepareError> {
        let (positions, tets) = base_mesh(&self.base_spec(), ([0.0; 3], [0.0; 3]))?;
        Ok(BaseMesh {
            levels: self.lattice.levels,
            values: vec![f32::NAN; positions.len()],
            empty: vec![false; tets.len()],
            positions,
            tets,
            predictor: Predictor::Parent,
        })
    }

    /// The whole store's base mesh (its values and empty flags left to the parts).
    fn base_spec(&self) -> BaseSpec {
        BaseSpec::KuhnBoxes {
            lo: [0.0; 3],
            hi: self.lattice.hi,
            cells: self.lattice.cells,
        }
    }
}

/// `prepare --parts N --part K`: reads part `k`'s slab, analyses it and writes its files.
pub fn prepare_part(o: &PrepareOptions, n: u32, k: u32) -> Result<PartSummary, PrepareError> {
    if let Some(to) = super::remote::remote_out(o)? {
        return super::remote::prepare_part_to(o, n, k, &to);
    }
    let t0 = Instant::now();
    let plan = Plan::new(o, n)?;
    if k >= n {
        return Err(PrepareError::Usage(format!(
            "--part {k}: parts are numbered 0 to {}",
            n - 1
        )));
    }
    tracing::info!(part = k, parts = n, "the grid's value range");
    let range = plan.value_range(o.read.nan_as)?;
    part_in(o, &plan, k, range, t0)
}

/// Part `k` of `plan`, given the whole grid's value range.
fn part_in(
    o: &PrepareOptions,
    plan: &Plan,
    k: u32,
    range: (f32, f32),
    t0: Instant,
) -> Result<PartSummary, PrepareError> {
    let n = plan.n;
    let dir = part_dir(&o.out, n, k);
    std::fs::create_dir_all(&dir).map_err(|e| io_error(&dir, e))?;
    // a summary left by an earlier run of this part is not this run's
    remove_if_there(&dir.join(SUMMARY_FILE))?;

    let PartBox { rows, layers } = plan.part_box(k);
    let side = 1usize << plan.lattice.levels;
    let voxels = |cells: &std::ops::Range<usize>, n: usize| {
        cells.start * side..(cells.end * side).min(n - 1) + 1
    };
    let (y, z) = (voxels(&rows, plan.dims[1]), voxels(&layers, plan.dims[2]));
    tracing::info!(part = k, ?rows, ?layers, voxel_rows = ?y, voxel_planes = ?z, "reading the part's block");
    let grid = plan.grid.read_block(&plan.path, o.read.nan_as, y, z)?;
    let (spec, levels, domain) = super::voxel_base(&grid, Some(plan.lattice.levels))?;
    let BaseSpec::KuhnBoxes { cells, .. } = spec else {
        unreachable!("a raw grid's base is Kuhn boxes")
    };
    debug_assert_eq!(cells, [plan.lattice.cells[0], rows.len(), layers.len()]);
    let domain_box = domain.and_then(|d| match d {
        super::Domain::Box { lo, hi } => Some([lo, hi]),
        super::Domain::Mesh(_) => None,
    });
    let mut r = resample(&Source::Raw(grid), &spec, levels)?;
    if r.outside > 0 {
        return Err(PrepareError::Usage(format!(
            "part {k}: {} vertices outside a raw grid's lattice",
            r.outside
        )));
    }
    r.base.predictor = Predictor::Parent;
    tracing::info!(part = k, vertices = r.samples.len(), "analysing the part");
    let a = analyze_hierarchy_in_range(r, plan.precision, o.progress, Some(range))?;

    // the planes shared with lower-id parts (the layer below, the rows before in this layer):
    // their owners are there, and the vertices are counted there. Per base vertex of the part, a
    // bit per such plane it lies on: bit 0 its first plane of corners along z, bit 1 along y.
    let [cx, _, _] = plan.lattice.cells;
    let (sx, sy) = (cx as u64 + 1, rows.len() as u64 + 1);
    let planes = |v: u32| -> u8 {
        let (j, kk) = ((v as u64 / sx) % sy, v as u64 / (sx * sy));
        ((layers.start > 0 && kk == 0) as u8) | (((rows.start > 0 && j == 0) as u8) << 1)
    };
    // the lower planes holding a lattice point of base tet `tet` (weights `w`): those of all the
    // corners it depends on
    let point_planes = |tet: u32, w: &[u32; 4]| -> u8 {
        let t = &a.base.tets[tet as usize];
        (0..4)
            .filter(|&i| w[i] != 0)
            .fold(0b11, |m, i| m & planes(t[i]))
    };
    let on_lower = |tet: u32, w: &[u32; 4]| point_planes(tet, w) != 0;
    let histogram = store::histogram_inside(
        &a.base,
        &a.reference,
        None,
        domain_box,
        [range.0, range.1],
        |t, w| !on_lower(t, w),
    );

    let whole = Forest::new(n_base_of(plan), levels);
    let sub = a.base.forest();
    let [_, cy, _] = plan.lattice.cells;
    let b0 = 6 * ((layers.start * cy + rows.start) * cx) as u64;
    let path = dir.join(NODES_FILE);
    let file = std::fs::File::create(&path).map_err(|e| io_error(&path, e))?;
    let mut w = HashingWriter::new(BufWriter::new(file));
    let mut node_ranges = Vec::with_capacity(levels as usize);
    let mut coefficients = 0u64;
    let mut at = 0usize;
    // the nodes coded as a store codes them, in blocks of at most BLOCK consecutive ids of one
    // level (the finish decodes them and codes the store's blocks)
    let coder = part_coder(&plan.whole_base()?, a.quantizer);
    let mut block = Vec::with_capacity(store::BLOCK as usize);
    let mut put = |nodes: &mut Vec<DetailNode>| -> Result<(), PrepareError> {
        if nodes.is_empty() {
            return Ok(());
        }
        let bad = |e: String| PrepareError::Usage(format!("{}: {e}", path.display()));
        let coded = coder.encode(nodes).map_err(|e| bad(e.to_string()))?;
        bincode::serde::encode_into_std_write(&coded, &mut w, bincode::config::standard())
            .map_err(|e| bad(e.to_string()))?;
        nodes.clear();
        Ok(())
    };
    for l in 0..levels {
        let (s, e) = (sub.level_start(l), sub.level_start(l + 1));
        let first = whole.level_start(l) + b0 * (1u64 << (3 * l as u32));
        node_ranges.push([first, first + (e - s)]);
        for (id, t) in LevelWalker::new(sub, l, s..e) {
            let i = id as usize;
            let mask = a.owned[i];
            let mine = &a.coeffs[at..at + mask.count_ones() as usize];
            at += mine.len();
            let (mut owned, mut coeffs) = (0u8, Vec::with_capacity(mine.len()));
            let mut c = mine.iter();
            for (bit, &(u, v)) in EDGES.iter().enumerate() {
                if mask & (1 << bit) == 0 {
                    continue;
                }
                let d = *c.next().expect("one coefficient a bit");
                // an edge on a lower plane: both ends on the same one
                if point_planes(t.base, &t.v[u]) & point_planes(t.base, &t.v[v]) == 0 {
                    owned |= 1 << bit;
                    coeffs.push(d);
                }
            }
            coefficients += coeffs.len() as u64;
            let node = DetailNode {
                id: first + (id - s),
                owned,
                empty_children: a.empty_children[i],
                subtree_max_abs: a.subtree_max_abs[i],
                coeffs,
            };
            block.push(node);
            if block.len() == store::BLOCK as usize {
                put(&mut block)?;
            }
        }
        put(&mut block)?;
    }
    let (nodes_bytes, nodes_crc32) = w.finish().map_err(|e| io_error(&path, e))?;
    let global_point = |v: u64| {
        let (i, j, kk) = (v % sx, (v / sx) % sy, v / (sx * sy));
        i + sx * ((rows.start as u64 + j) + (cy as u64 + 1) * (layers.start as u64 + kk))
    };
    let summary = PartSummary {
        format: PART_FORMAT.into(),
        parts: n,
        part: k,
        options: plan.fingerprint.clone(),
        base_tets: [b0, b0 + sub.n_base],
        node_ranges,
        coefficients,
        nodes_bytes,
        nodes_crc32,
        value_range: [a.value_range.0, a.value_range.1],
        max_abs_error: a.max_abs_error,
        error_bound: a.error_bound,
        quantizer: a.quantizer,
        histogram,
        base_values: a
            .base
            .values
            .iter()
            .enumerate()
            .map(|(v, &x)| (global_point(v as u64), x))
            .collect(),
        empty_base_tets: (0..sub.n_base)
            .filter(|&b| a.base.empty[b as usize])
            .map(|b| b0 + b)
            .collect(),
        seconds: t0.elapsed().as_secs_f64(),
    };
    // the summary last, whole or not at all: a part without one is not done
    let text = serde_json::to_string_pretty(&summary).expect("a part summary serializes");
    let tmp = dir.join(format!("{SUMMARY_FILE}.partial"));
    std::fs::write(&tmp, text).map_err(|e| io_error(&tmp, e))?;
    let done = dir.join(SUMMARY_FILE);
    std::fs::rename(&tmp, &done).map_err(|e| io_error(&done, e))?;
    Ok(summary)
}

fn n_base_of(plan: &Plan) -> u64 {
    6 * plan.lattice.cells.iter().product::<usize>() as u64
}

/// What a process holds besides its part: the binary, its threads' stacks, I/O buffers, the base
/// mesh (measured: 20–30 MB on this machine; with a margin).
pub const PROCESS_OVERHEAD: u64 = 64 << 20;

/// The memory a part of `rows` rows of `layers` layers of boxes of `lattice` needs: its block of
/// voxels, and its vertices at [`PREPARE_BYTES_PER_VERTEX`] each (all rows and layers: the
/// whole grid).
pub fn part_bytes(
    lattice: &VoxelLattice,
    dims: [usize; 3],
    dtype_bytes: usize,
    rows: usize,
    layers: usize,
) -> u64 {
    let side = 1u64 << lattice.levels;
    let (lattice_rows, lattice_planes) = (rows as u64 * side + 1, layers as u64 * side + 1);
    let px = lattice.points[0] as u64;
    let (voxel_rows, voxel_planes) = (
        lattice_rows.min(dims[1] as u64),
        lattice_planes.min(dims[2] as u64),
    );
    (px * lattice_rows * lattice_planes).saturating_mul(PREPARE_BYTES_PER_VERTEX)
        + dims[0] as u64 * voxel_rows * voxel_planes * dtype_bytes as u64
}

/// Why `o` cannot be prepared by parts, if it cannot (what the parts refuse besides the
/// number of parts).
pub fn out_of_core_refusal(o: &PrepareOptions) -> Option<&'static str> {
    if o.preview.is_some() {
        Some("--preview")
    } else if o.keep_reference {
        Some("--keep-reference")
    } else if o.bits.is_some() {
        Some("--bits")
    } else if o.predictor == super::PredictorChoice::Axes {
        Some("--predictor axes")
    } else {
        None
    }
}

/// How [`prepare_out_of_core`] splits a grid: its levels, parts, and what a part takes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct OutOfCore {
    pub levels: u8,
    pub parts: u32,
    pub layers_per_part: usize,
    /// The rows of boxes a part takes (all of them when it takes whole layers).
    pub rows_per_part: usize,
    /// [`part_bytes`] of the largest part, with [`PROCESS_OVERHEAD`].
    pub part_bytes: u64,
}

/// The split [`prepare_out_of_core`] makes of `o`'s grid within `memory`: `--levels`, or the most
/// levels (up to the grid's default, with at most 4,096 boxes) at which one layer of boxes, or
/// else one row of boxes, fits; as many layers (or rows of one layer) a part as fit.
pub fn out_of_core_plan(o: &PrepareOptions, memory: u64) -> Result<OutOfCore, PrepareError> {
    let dims = o
        .read
        .grid
        .dims
        .ok_or(crate::resample::raw::RawError::MissingDims)?;
    let dtype = crate::resample::raw::RawType::parse(&o.read.grid.dtype)
        .ok_or_else(|| PrepareError::UnknownDtype(o.read.grid.dtype.clone()))?;
    let spacing = o.read.grid.spacing;
    let budget = memory.saturating_sub(PROCESS_OVERHEAD);
    let candidates: Vec<u8> = match o.levels {
        Some(l) => vec![l],
        None => {
            let top = VoxelLattice::fit(dims, spacing, None, indexable)?.levels;
            (1..=top).rev().collect()
        }
    };
    let mut chosen = None;
    let mut least = u64::MAX;
    for &l in &candidates {
        let lattice = VoxelLattice::at(dims, spacing, l);
        let cells: usize = lattice.cells.iter().product();
        // automatic levels keep the base mesh a client receives first as small as a grid's
        // default does
        if 6 * cells > MOST_BASE_TETS || (o.levels.is_none() && cells > MOST_AUTO_CELLS) {
            continue;
        }
        let [_, cy, cz] = lattice.cells;
        let bytes = |rows, layers| part_bytes(&lattice, dims, dtype.bytes(), rows, layers);
        least = least.min(bytes(1, 1) + PROCESS_OVERHEAD);
        // whole layers, as many as fit; else rows of one layer, as many as fit
        let most = |n: usize, f: &dyn Fn(usize) -> bool| (1..=n).take_while(|&k| f(k)).last();
        if let Some(per) = most(cz, &|k| bytes(cy, k) <= budget) {
            chosen = Some((lattice, cz.div_ceil(per), per, cy));
            break;
        }
        if let Some(per) = most(cy, &|r| bytes(r, 1) <= budget) {
            chosen = Some((lattice, cz * cy.div_ceil(per), 1, per));
            break;
        }
    }
    let Some((lattice, n, layers_per_part, rows_per_part)) = chosen else {
        return Err(PrepareError::MemoryTooSmall {
            memory,
            least,
            least_mib: least.div_ceil(1 << 20),
            per_vertex: PREPARE_BYTES_PER_VERTEX,
            overhead: PROCESS_OVERHEAD,
        });
    };
    Ok(OutOfCore {
        levels: lattice.levels,
        parts: n as u32,
        layers_per_part,
        rows_per_part,
        part_bytes: part_bytes(
            &lattice,
            dims,
            dtype.bytes(),
            rows_per_part,
            layers_per_part,
        ) + PROCESS_OVERHEAD,
    })
}

/// `prepare` of a raw grid whose hierarchy does not fit `memory`: by parts in this process, one
/// after the other, then the finish; parts an earlier run cut short left done are kept. The split
/// is [`out_of_core_plan`]'s. Each part holds at most `memory` ([`part_bytes`] +
/// [`PROCESS_OVERHEAD`]); the finish holds a block.
pub fn prepare_out_of_core(o: &PrepareOptions, memory: u64) -> Result<Summary, PrepareError> {
    let t0 = Instant::now();
    let OutOfCore {
        levels,
        parts: n,
        layers_per_part,
        rows_per_part,
        part_bytes,
    } = out_of_core_plan(o, memory)?;
    let show = o.progress;
    let o = PrepareOptions {
        levels: Some(levels),
        progress: false,
        ..o.clone()
    };
    let plan = Plan::new(&o, n)?;
    tracing::info!(
        levels,
        boxes = ?plan.lattice.cells,
        parts = n,
        layers_per_part,
        rows_per_part,
        part_bytes,
        "out of core: by parts in this process"
    );
    let bar = if show {
        let b = indicatif::ProgressBar::new(n as u64);
        b.set_style(
            indicatif::ProgressStyle::with_template(
                "{msg} [{bar:30}] {pos}/{len} parts, {elapsed} (ETA {eta})",
            )
            .expect("a valid template"),
        );
        b.set_message("prepare by parts");
        b
    } else {
        indicatif::ProgressBar::hidden()
    };
    let range = plan.value_range(o.read.nan_as)?;
    for k in 0..n {
        if part_done(&o.out, &plan, k) {
            tracing::info!(part = k, "already done (an earlier run's): kept");
        } else {
            part_in(&o, &plan, k, range, Instant::now())?;
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    let mut s = finish(&o, n)?;
    s.seconds = t0.elapsed().as_secs_f64();
    Ok(s)
}

/// Part `k`'s summary, `None` when the part is not done; refused when it belongs to another
/// plan (another part, count, input or options).
fn read_summary(out: &Path, plan: &Plan, k: u32) -> Result<Option<PartSummary>, PrepareError> {
    let n = plan.n;
    let path = part_dir(out, n, k).join(SUMMARY_FILE);
    let text = match std::fs::read_to_string(&path) {
        Ok(text) => text,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(io_error(&path, e)),
    };
    let p: PartSummary = serde_json::from_str(&text)
        .map_err(|e| PrepareError::Usage(format!("{}: not a part summary: {e}", path.display())))?;
    if p.format != PART_FORMAT || p.parts != n || p.part != k {
        return Err(PrepareError::Usage(format!(
            "{}: part {} of {} ({}), not part {k} of {n}",
            path.display(),
            p.part,
            p.parts,
            p.format
        )));
    }
    if p.options != plan.fingerprint {
        return Err(PrepareError::Usage(format!(
            "part {k} was prepared with other options or another input ({:?}) than these \
             ({:?}): run it again with these",
            p.options, plan.fingerprint
        )));
    }
    Ok(Some(p))
}

/// Whether part `k` is done and whole: its summary is this plan's and its node file is what it
/// wrote (a prepare cut short resumes at the first part that is not).
fn part_done(out: &Path, plan: &Plan, k: u32) -> bool {
    let Ok(Some(p)) = read_summary(out, plan, k) else {
        return false;
    };
    let path = part_dir(out, plan.n, k).join(NODES_FILE);
    checksum(&path).is_ok_and(|c| c == (p.nodes_bytes, p.nodes_crc32))
}

/// The coder of the parts' node files: a store's, of the whole base mesh (its ownership), with a
/// part's quantizer.
fn part_coder(whole: &BaseMesh, quantizer: Option<Quantizer>) -> BlockCoder {
    let encoding = Encoding::of(quantizer.map(|q| (q, LevelSteps::UNIFORM)));
    BlockCoder::new(whole, &encoding)
}

/// `prepare --parts N --finish`: the store from the parts' files.
pub fn finish(o: &PrepareOptions, n: u32) -> Result<Summary, PrepareError> {
    let t0 = Instant::now();
    let plan = Plan::new(o, n)?;
    let mut parts = Vec::with_capacity(n as usize);
    let mut missing = Vec::new();
    for k in 0..n {
        match read_summary(&o.out, &plan, k)? {
            Some(p) => parts.push(p),
            None => missing.push(k),
        }
    }
    if !missing.is_empty() {
        let list: Vec<String> = missing.iter().map(|k| k.to_string()).collect();
        return Err(PrepareError::Usage(format!(
            "{} of {n} parts are not done (part {}): run `prepare … --parts {n} --part K` for \
             each, then --finish again; nothing was written",
            missing.len(),
            list.join(", part ")
        )));
    }

    let levels = plan.lattice.levels;
    let mut base = plan.whole_base()?;
    let forest = base.forest();
    for p in &parts {
        for &(v, x) in &p.base_values {
            let slot = base.values.get_mut(v as usize).ok_or_else(|| {
                PrepareError::Usage(format!(
                    "part {}: base vertex {v} of {}",
                    p.part, forest.n_base
                ))
            })?;
            if !slot.is_nan() && slot.to_bits() != x.to_bits() {
                return Err(PrepareError::Usage(format!(
                    "parts disagree on base vertex {v}: {slot} and {x} (part {})",
                    p.part
                )));
            }
            *slot = x;
        }
        for &b in &p.empty_base_tets {
            if let Some(e) = base.empty.get_mut(b as usize) {
                *e = true;
            }
        }
    }
    if let Some(v) = base.values.iter().position(|x| x.is_nan()) {
        return Err(PrepareError::Usage(format!(
            "no part gave base vertex {v} a value"
        )));
    }
    let first = &parts[0];
    let same = |what: &str, ok: bool| -> Result<(), PrepareError> {
        if ok {
            Ok(())
        } else {
            Err(PrepareError::Usage(format!(
                "the parts disagree on the {what}"
            )))
        }
    };
    same(
        "value range",
        parts.iter().all(|p| p.value_range == first.value_range),
    )?;
    same(
        "error bound",
        parts.iter().all(|p| p.error_bound == first.error_bound),
    )?;
    same(
        "quantizer's step",
        parts
            .iter()
            .all(|p| p.quantizer.map(|q| q.step) == first.quantizer.map(|q| q.step)),
    )?;
    // the width the one-process analysis sizes from every detail: the widest part's (a code
    // codes alike at any width that holds it)
    let quantizer = first.quantizer.map(|q| Quantizer {
        bits: parts
            .iter()
            .filter_map(|p| p.quantizer.map(|q| q.bits))
            .max()
            .unwrap_or(q.bits),
        ..q
    });
    let mut histogram = vec![0u64; first.histogram.len()];
    for p in &parts {
        same("histogram", p.histogram.len() == histogram.len())?;
        for (h, c) in histogram.iter_mut().zip(&p.histogram) {
            *h += c;
        }
    }
    let totals = Totals {
        vertices: base.vertex_keys().vertex_count(),
        coefficients: parts.iter().map(|p| p.coefficients).sum(),
        value_range: (first.value_range[0], first.value_range[1]),
        max_abs_error: parts.iter().map(|p| p.max_abs_error).fold(0.0, f64::max),
        error_bound: first.error_bound,
        histogram,
    };

    // the parts' node files whole and as written, before a byte of the store is
    let mut readers = Vec::with_capacity(parts.len());
    for p in &parts {
        let path = part_dir(&o.out, n, p.part).join(NODES_FILE);
        let (len, crc) = checksum(&path)?;
        if (len, crc) != (p.nodes_bytes, p.nodes_crc32) {
            return Err(PrepareError::Usage(format!(
                "{}: {len} bytes with CRC-32 {crc:08x} where part {} wrote {} bytes with \
                 {:08x}: run the part again, then --finish",
                path.display(),
                p.part,
                p.nodes_bytes,
                p.nodes_crc32
            )));
        }
        let file = std::fs::File::open(&path).map_err(|e| io_error(&path, e))?;
        let coder = part_coder(&base, p.quantizer);
        readers.push((path, BufReader::new(file), coder, VecDeque::new()));
    }
    // the nodes level by level, each level part by part: (part, node count) runs, walked
    // without holding a word a node
    let runs: Vec<(usize, u64)> = (0..levels as usize)
        .flat_map(|l| {
            parts
                .iter()
                .enumerate()
                .map(move |(i, p)| (i, p.node_ranges[l][1] - p.node_ranges[l][0]))
        })
        .collect();
    let mut runs = runs.into_iter();
    let mut run: (usize, u64) = (0, 0);
    let mut next_part = move || -> Option<usize> {
        while run.1 == 0 {
            run = runs.next()?;
        }
        run.1 -= 1;
        Some(run.0)
    };
    let mut stream = std::iter::from_fn(move || {
        let (path, r, coder, decoded) = &mut readers[next_part()?];
        if decoded.is_empty() {
            let block = bincode::serde::decode_from_std_read::<NodeBlock, _, _>(
                r,
                bincode::config::standard(),
            );
            let nodes = block
                .map_err(|e| e.to_string())
                .and_then(|b| coder.decode(&b).map_err(|e| e.to_string()));
            match nodes {
                Ok(nodes) => decoded.extend(nodes),
                Err(e) => return Some(Err(format!("{}: {e}", path.display()))),
            }
        }
        Some(
            decoded
                .pop_front()
                .ok_or_else(|| format!("{}: an empty block", path.display())),
        )
    });
    let lo = [0.0; 3];
    let hi = [0, 1, 2].map(|a| (plan.dims[a] - 1) as f64 * plan.grid.spacing[a]);
    let levelset_near = plan
        .lattice
        .pads(plan.dims)
        .then(|| NearLevelSet::of_box(lo, hi))
        .transpose()?;
    let dataset = super::dataset_name(&plan.path, &o.input);
    let meta = StoreMeta {
        dataset,
        source: o.input.clone(),
        base: plan.base_spec().name(),
        outside_vertices: 0,
        source_value_range: Some((first.value_range[0], first.value_range[1])),
        levelset: None,
        levelset_near,
        preview: None,
        keep_reference: false,
        physical: plan
            .grid
            .volume
            .as_ref()
            .and_then(super::VolumeInput::physical),
    };
    let quantizer = quantizer.map(|q| (q, LevelSteps::UNIFORM));
    let m = store::write_streamed(
        &o.out,
        &base,
        quantizer,
        (forest.nodes(), &mut stream),
        &totals,
        None,
        meta,
    )?;
    let parts_dir = o.out.join("parts");
    std::fs::remove_dir_all(&parts_dir).map_err(|e| io_error(&parts_dir, e))?;
    let mut summary = Summary::of(&m, o, Predictor::Parent, None, t0);
    summary.volume = super::VolumeSummary::of(&plan.grid);
    Ok(summary)
}

fn io_error(path: &Path, e: std::io::Error) -> PrepareError {
    PrepareError::Store(StoreError::Io {
        path: path.to_path_buf(),
        source: e,
    })
}

fn remove_if_there(path: &Path) -> Result<(), PrepareError> {
    match std::fs::remove_file(path) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(io_error(path, e)),
        _ => Ok(()),
    }
}

/// A writer that counts and checksums what passes through it.
struct HashingWriter<W: Write> {
    inner: W,
    hasher: crc32fast::Hasher,
    bytes: u64,
}

impl<W: Write> HashingWriter<W> {
    fn new(inner: W) -> Self {
        HashingWriter {
            inner,
            hasher: crc32fast::Hasher::new(),
            bytes: 0,
        }
    }

    /// Flushes; the bytes written and their CRC-32.
    fn finish(mut self) -> std::io::Result<(u64, u32)> {
        self.inner.flush()?;
        Ok((self.bytes, self.hasher.finalize()))
    }
}

impl<W: Write> Write for HashingWriter<W> {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let n = self.inner.write(buf)?;
        self.hasher.update(&buf[..n]);
        self.bytes += n as u64;
        Ok(n)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.inner.flush()
    }
}

/// A file's size and CRC-32, read through.
fn checksum(path: &Path) -> Result<(u64, u32), PrepareError> {
    let mut f = std::fs::File::open(path).map_err(|e| io_error(path, e))?;
    let mut w = HashingWriter::new(std::io::sink());
    std::io::copy(&mut f, &mut w).map_err(|e| io_error(path, e))?;
    w.finish().map_err(|e| io_error(path, e))
}
