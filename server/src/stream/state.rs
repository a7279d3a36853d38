//! [`Shared`]: what every connection and request shares: the store, the frames that never change
//! (manifest, base), per-node metadata (subtree maxima, the magnitude and random orders, bounding
//! spheres) and, when small enough, every node.

use super::admission::{Admission, PeerBudgets};
use super::auth::FailureLimiter;
use super::config::{ServeConfig, ViewCriterion, ViewTf};
use super::error::ServeError;
use crate::render_service::RenderService;
use axum::body::Bytes;
use glam::DVec3;
use std::collections::VecDeque;
use std::sync::atomic::{AtomicU64, Ordering as AtomicOrdering};
use std::sync::{Arc, Mutex, OnceLock};
use tetwave_protocol::block::{BlockCoder, NodeBlock};
use tetwave_protocol::node::resolve_bound;
use tetwave_protocol::order::shuffle;
use tetwave_protocol::store_format::LEVELSET_BAND_FILE;
use tetwave_protocol::view::{tet_sphere, DEFAULT_IMAGE_EPS};
use tetwave_protocol::wire::{encode, ServerMsg, SessionStart};
use tetwave_protocol::{DetailNode, Forest, LatticeTet, TetId};
use tetwave_render::transfer::{TransferFunction, ValueHistogram};
use tetwave_store::Manifest;
use tetwave_store::{OpenOptions, Store, StoreError, BLOCK};

/// Per-node geometry for view-dependent order: bounding spheres, in world units, and the image
/// weights the client's default selection gives the nodes.
pub(super) struct Geometry {
    pub(super) centre: Vec<[f32; 3]>,
    /// Bounding-sphere radius ([`tet_sphere`]).
    pub(super) radius: Vec<f32>,
    /// Every node's [`ImageCriterion::node_weight`] under the `default` transfer function over
    /// the store's value range, read off what the store's nodes synthesize; `None` under
    /// [`ViewCriterion::Data`].
    pub(super) image: Option<Vec<f32>>,
    /// The same under `auto` (`default` fitted to the manifest's histogram), when the manifest
    /// has one: it is steeper where most of the data lies, so its clients need other nodes first.
    /// Computed when a session first asks for it ([`Shared::image_weights`]).
    image_auto: OnceLock<Option<Vec<f32>>>,
}

/// The transfer function streaming clients draw with by default.
fn default_tf() -> TransferFunction {
    TransferFunction::preset("default").expect("the default preset exists")
}

/// Ids per parallel task when the per-node geometry is computed.
const GEOMETRY_CHUNK: u64 = 1 << 14;

/// [`Geometry::image`]: per level, the parents' 10 split points' values give each
/// child its corners and the midpoint deviation of its corners created at its level.
fn image_weights(
    store: &Store,
    forest: Forest,
    smax: &[f32],
    radius: &[f32],
    values: &[f32],
    tf: &TransferFunction,
) -> Vec<f32> {
    use rayon::prelude::*;
    use tetwave_protocol::hierarchy::{LevelWalker, BEY_CHILDREN, EDGES};
    let base = &store.base;
    let keys = base.vertex_keys();
    let img = tf.image_criterion(store.manifest.value_range, base, DEFAULT_IMAGE_EPS);
    let levels = forest.levels;
    let n = forest.nodes() as usize;
    let mut w = vec![1.0f32; n];
    // base tets (level 0) have an unknown bound: weight 1
    for l in 1..levels {
        let (p0, p1) = (forest.level_start(l - 1), forest.level_start(l));
        let c0 = forest.level_start(l) as usize;
        let c1 = forest.level_start(l + 1).min(n as u64) as usize;
        w[c0..c1]
            .par_chunks_mut(8 * GEOMETRY_CHUNK as usize)
            .enumerate()
            .for_each(|(k, out)| {
                let a = p0 + k as u64 * GEOMETRY_CHUNK;
                let b = (a + GEOMETRY_CHUNK).min(p1);
                for (j, (pid, t)) in LevelWalker::new(forest, l - 1, a..b).enumerate() {
                    let pts = t.split_points();
                    let v: [f32; 10] =
                        std::array::from_fn(|i| values[keys.key(t.base, &pts[i]) as usize]);
                    for (i, corners) in BEY_CHILDREN.iter().enumerate() {
                        let id = forest.child(pid, i) as usize;
                        let mut curvature = 0.0f64;
                        for &c in corners {
                            if c >= 4 {
                                let (e0, e1) = EDGES[c - 4];
                                let mid = 0.5 * (v[e0] as f64 + v[e1] as f64);
                                curvature = curvature.max((v[c] as f64 - mid).abs());
                            }
                        }
                        let vals = corners.map(|c| v[c]);
                        out[8 * j + i] = img.node_weight(
                            vals,
                            curvature,
                            l,
                            levels,
                            smax[id],
                            2.0 * radius[id] as f64,
                        ) as f32;
                    }
                }
            });
    }
    w
}

/// What every connection shares: the store, encoded frames that never change, per-node metadata.
pub struct Shared {
    pub store: Store,
    pub config: ServeConfig,
    forest: Forest,
    pub(super) nodes: u64,
    pub(super) manifest_json: Bytes,
    /// A session's first frame: `ServerMsg::Start`.
    pub(super) start_frame: Bytes,
    /// `GET /v1/base`'s frame: `ServerMsg::Base`.
    pub(super) base_frame: Bytes,
    /// The coded near band of the domain's level set (`/v1/levelset`), when the store has one.
    pub(super) levelset_near: Option<Bytes>,
    /// Every node, when the store is small enough ([`ServeConfig::cache_limit_bytes`]).
    cache: Option<Vec<DetailNode>>,
    /// Otherwise the last decoded blocks of the store, most recent last ([`BLOCK_CACHE`]).
    recent: Mutex<VecDeque<(u64, Arc<Vec<DetailNode>>)>>,
    /// Blocks found in `recent`, and read from the store (`/healthz`, `/metrics`).
    pub(super) block_hits: AtomicU64,
    pub(super) block_reads: AtomicU64,
    /// `subtree_max_abs` of every node.
    pub(super) smax: Vec<f32>,
    /// The store's preview and its coder, when it has one and new sessions get some of it
    /// ([`ServeConfig::preview_share`]).
    pub(super) preview: Option<ServedPreview>,
    magnitude_perm: OnceLock<Arc<Vec<TetId>>>,
    random_perm: OnceLock<Arc<Vec<TetId>>>,
    geometry: OnceLock<Arc<Geometry>>,
    pub(super) connections: AtomicU64,
    /// View-order rescans over every connection (`/healthz` reports it).
    pub(super) view_rescans: AtomicU64,
    pub render: RenderService,
    /// Open connections and streams.
    pub(super) admission: Arc<Admission>,
    /// Stream control work per peer.
    pub(super) budgets: PeerBudgets,
    /// Wrong tokens per peer.
    pub(super) auth_failures: FailureLimiter,
    /// Renders run one at a time (the queue in front is a concurrency limit on the route).
    pub(super) render_run: tokio::sync::Mutex<()>,
}

/// A store's preview as connections send it.
pub(super) struct ServedPreview {
    /// Nodes `0..nodes.len()`, in id order.
    pub(super) nodes: Vec<DetailNode>,
    pub(super) coder: BlockCoder,
    /// Most bytes of preview blocks one session gets.
    pub(super) budget: u64,
    /// The sending order for view order (made at the first such session; the others send by
    /// increasing id).
    pub(super) view_order: OnceLock<Arc<Vec<TetId>>>,
    /// Estimated bytes per node by level, for sizing batches (made at the first session).
    pub(super) level_costs: OnceLock<Vec<f64>>,
}

/// Decoded store blocks kept when the store is not cached whole: batches of neighbouring
/// connections and consecutive batches of one connection often touch the same blocks, and a
/// decoded block of [`BLOCK`] nodes takes a few hundred kilobytes.
const BLOCK_CACHE: usize = 32;

impl Shared {
    /// Opens the store and prepares what connections share.
    pub fn open(dir: &std::path::Path, config: ServeConfig) -> Result<Arc<Shared>, ServeError> {
        // the structural check decodes every block once: take the subtree bounds, and every
        // node while their rough in-memory size (the struct, its allocation, its coefficients)
        // stays within the cache limit
        let per_node = std::mem::size_of::<DetailNode>() as u64 + 16;
        let mut smax: Vec<f32> = Vec::new();
        let mut cache: Option<Vec<DetailNode>> = Some(Vec::new());
        let mut est = 0u64;
        let mut store = Store::open_visiting(
            dir,
            OpenOptions {
                verify_checksums: config.verify_checksums,
                ..Default::default()
            },
            |part| {
                smax.extend(part.iter().map(|n| n.subtree_max_abs));
                est += part
                    .iter()
                    .map(|n| per_node + 4 * n.coeffs.len() as u64)
                    .sum::<u64>();
                if est > config.cache_limit_bytes {
                    cache = None;
                }
                if let Some(c) = cache.as_mut() {
                    c.extend(part);
                }
            },
        )?;
        let forest = store.forest();
        // finest-level nodes carry no bound of their own: their parent's (an earlier id) stands in
        for i in 0..smax.len() {
            let parent = || {
                forest
                    .parent(i as u64)
                    .and_then(|p| smax.get(p as usize).copied())
            };
            smax[i] = resolve_bound(smax[i], parent);
        }
        let nodes = store.manifest.counts.nodes;
        if nodes > u32::MAX as u64 {
            return Err(ServeError::TooLarge(nodes));
        }
        let served = served_manifest(&store.manifest);
        let manifest_json = Bytes::from(
            serde_json::to_vec_pretty(&served).map_err(|e| ServeError::Encode(e.to_string()))?,
        );
        let start_frame = Bytes::from(
            encode(&ServerMsg::Start(Box::new(SessionStart {
                manifest: served,
                base: store.base.clone(),
            })))
            .map_err(|e| ServeError::Encode(e.to_string()))?,
        );
        let base_frame = Bytes::from(
            encode(&ServerMsg::Base(Box::new(store.base.clone())))
                .map_err(|e| ServeError::Encode(e.to_string()))?,
        );
        // decoded once here, so a corrupt band is refused at start, not on a client's request
        let levelset_near = store.read_levelset_near()?.map(|(b, _)| Bytes::from(b));
        let keep = cache.is_some();
        tracing::info!(
            nodes,
            cached = keep,
            "store {} opened for serving",
            dir.display()
        );
        let budget = store
            .manifest
            .files
            .get("blocks.bin")
            .map_or(0, |f| f.bytes) as f64
            * config.preview_share;
        let preview = match (store.preview.take(), &store.manifest.preview) {
            (Some(nodes), Some(p)) if budget >= 1.0 => Some(ServedPreview {
                view_order: OnceLock::new(),
                level_costs: OnceLock::new(),
                nodes,
                coder: BlockCoder::for_preview(&store.base, &p.encoding),
                budget: budget as u64,
            }),
            _ => None,
        };
        let render = RenderService::new(dir);
        let admission = Admission::new(config.limits.clone());
        Ok(Arc::new(Shared {
            store,
            config,
            forest,
            nodes,
            manifest_json,
            start_frame,
            base_frame,
            levelset_near,
            cache,
            recent: Mutex::new(VecDeque::with_capacity(BLOCK_CACHE)),
            block_hits: AtomicU64::new(0),
            block_reads: AtomicU64::new(0),
            smax,
            preview,
            magnitude_perm: OnceLock::new(),
            random_perm: OnceLock::new(),
            geometry: OnceLock::new(),
            connections: AtomicU64::new(0),
            view_rescans: AtomicU64::new(0),
            render,
            admission,
            auth_failures: FailureLimiter::default(),
            budgets: PeerBudgets::default(),
            render_run: tokio::sync::Mutex::new(()),
        }))
    }

    /// Number of detail nodes.
    pub fn nodes(&self) -> u64 {
        self.nodes
    }

    /// Open WebSocket connections.
    pub fn connections(&self) -> u64 {
        self.connections.load(AtomicOrdering::Relaxed)
    }

    /// Every id, largest subtree max |detail| first, ties by id; computed once.
    pub(super) fn magnitude_perm(&self) -> Arc<Vec<TetId>> {
        self.magnitude_perm
            .get_or_init(|| {
                let mut p: Vec<TetId> = (0..self.nodes).collect();
                // largest first; ties by id (coarse before fine)
                p.sort_by(|&a, &b| {
                    self.smax[b as usize]
                        .total_cmp(&self.smax[a as usize])
                        .then(a.cmp(&b))
                });
                Arc::new(p)
            })
            .clone()
    }

    /// Every id, shuffled with [`ServeConfig::seed`]; computed once.
    pub(super) fn random_perm(&self) -> Arc<Vec<TetId>> {
        self.random_perm
            .get_or_init(|| {
                let mut p: Vec<TetId> = (0..self.nodes).collect();
                shuffle(&mut p, self.config.seed);
                Arc::new(p)
            })
            .clone()
    }

    /// Computes what view order reads (`Self::geometry`) on a thread of its own, so that the
    /// first session in view order does not pay for it (a session that asks before it is done
    /// waits for the same computation, not a second one).
    pub fn warm_view_order(self: &Arc<Self>) {
        let s = Arc::clone(self);
        let spawned = std::thread::Builder::new()
            .name("view-order".into())
            .spawn(move || {
                s.geometry();
            });
        if let Err(e) = spawned {
            tracing::warn!("view order is computed by the first session that needs it: {e}");
        }
    }

    /// Whether a session in the configured order starts at once: always, but in view order
    /// before its geometry is computed ([`Self::warm_view_order`]).
    pub(super) fn view_order_ready(&self) -> bool {
        self.config.order != super::config::Order::View || self.geometry.get().is_some()
    }

    /// Whether every node is held decoded (the store fits the cache limit): no block is read
    /// after the start.
    pub(super) fn caches_every_node(&self) -> bool {
        self.cache.is_some()
    }

    /// Every node's bounding sphere and image weight; computed when view order first asks (or by
    /// [`Self::warm_view_order`]).
    pub(super) fn geometry(&self) -> Arc<Geometry> {
        self.geometry
            .get_or_init(|| {
                use rayon::prelude::*;
                let t0 = std::time::Instant::now();
                let base = &self.store.base;
                let forest = self.forest;
                let spheres: Vec<([f32; 3], f32)> = (0..self.nodes.div_ceil(GEOMETRY_CHUNK))
                    .into_par_iter()
                    .flat_map_iter(|k| {
                        let a = k * GEOMETRY_CHUNK;
                        (a..(a + GEOMETRY_CHUNK).min(self.nodes)).map(move |id| {
                            let t = LatticeTet::from_id(&forest, id);
                            let (c, r) = tet_sphere(
                                t.v.map(|w| DVec3::from_array(base.position(t.base, &w))),
                            );
                            (c.to_array(), r)
                        })
                    })
                    .collect();
                let (centre, radius): (Vec<_>, Vec<_>) = spheres.into_iter().unzip();
                // what streaming clients draw by default
                let image = match self.config.view_criterion {
                    ViewCriterion::Data => None,
                    ViewCriterion::Image => self.tf_weights(&radius, &default_tf()),
                };
                tracing::info!(
                    nodes = self.nodes,
                    image = image.is_some(),
                    "view-order geometry computed in {:.2} s",
                    t0.elapsed().as_secs_f64()
                );
                Arc::new(Geometry {
                    centre,
                    radius,
                    image,
                    image_auto: OnceLock::new(),
                })
            })
            .clone()
    }

    /// The image weights view order reads for a session drawing with `tf` (`None`: it weighs by
    /// details). `auto`'s are computed when a session first asks (a moment on a large store,
    /// on the session's blocking task); where the manifest has no histogram they are
    /// `default`'s, as the client's `auto` then is the preset.
    pub(super) fn image_weights<'g>(&self, g: &'g Geometry, tf: ViewTf) -> Option<&'g [f32]> {
        let default = g.image.as_deref();
        if tf == ViewTf::Default || default.is_none() {
            return default;
        }
        let auto = g.image_auto.get_or_init(|| {
            let t0 = std::time::Instant::now();
            let h = ValueHistogram::of_manifest(&self.store.manifest)?;
            let w = self.tf_weights(&g.radius, &default_tf().fitted(&h));
            tracing::info!(
                "view-order weights of auto computed in {:.2} s",
                t0.elapsed().as_secs_f64()
            );
            w
        });
        auto.as_deref().or(default)
    }

    /// Every node's image weight under `tf`, read off the values the store's own nodes
    /// synthesize (what a client that has every node draws; a store keeps no copy of its
    /// samples); `None` (and a warning) when the store does not synthesize.
    fn tf_weights(&self, radius: &[f32], tf: &TransferFunction) -> Option<Vec<f32>> {
        match self.store.synthesize_all() {
            Ok(values) => Some(image_weights(
                &self.store,
                self.forest,
                &self.smax,
                radius,
                &values,
                tf,
            )),
            Err(e) => {
                tracing::warn!(
                    "the store does not synthesize ({e}): view order weighs nodes by their \
                     details alone"
                );
                None
            }
        }
    }

    /// The nodes `ids` (in that order when cached, else in increasing id order).
    pub(super) fn forest(&self) -> Forest {
        self.forest
    }

    /// Nodes `ids` (sorted in place) as one coded block.
    pub(super) fn fetch_block(&self, ids: &mut [TetId]) -> Result<NodeBlock, ServeError> {
        let nodes = self.fetch(ids)?;
        // the store's own coder: batches and `/v1/nodes` ranges code as its blocks do
        self.store
            .coder()
            .encode(&nodes)
            .map_err(|e| ServeError::Encode(e.to_string()))
    }

    pub(super) fn fetch(&self, ids: &mut [TetId]) -> Result<Vec<DetailNode>, StoreError> {
        if let Some(c) = &self.cache {
            return Ok(ids.iter().map(|&i| c[i as usize].clone()).collect());
        }
        ids.sort_unstable();
        // the store holds coded blocks of BLOCK ids: decode each block the batch touches once
        let mut out = Vec::with_capacity(ids.len());
        let mut i = 0;
        while i < ids.len() {
            let b = ids[i] / BLOCK;
            let block = self.block(b)?;
            let first = b * BLOCK;
            while i < ids.len() && ids[i] / BLOCK == b {
                let node =
                    block
                        .get((ids[i] - first) as usize)
                        .ok_or_else(|| StoreError::Corrupt {
                            path: self.store.dir.join("blocks.bin"),
                            reason: format!("node {} is outside block {b}", ids[i]),
                        })?;
                out.push(node.clone());
                i += 1;
            }
        }
        Ok(out)
    }

    /// The decoded nodes of store block `b`, from the recent blocks or the store.
    fn block(&self, b: u64) -> Result<Arc<Vec<DetailNode>>, StoreError> {
        let lock = || self.recent.lock().unwrap_or_else(|e| e.into_inner());
        {
            let mut recent = lock();
            if let Some(k) = recent.iter().position(|(x, _)| *x == b) {
                let hit = recent.remove(k).expect("present");
                let nodes = hit.1.clone();
                recent.push_back(hit);
                self.block_hits
                    .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                return Ok(nodes);
            }
        }
        // decoded outside the lock: two connections may decode the same block at once, which
        // costs time but never a wrong answer
        self.block_reads
            .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let from = b * BLOCK;
        let nodes = Arc::new(
            self.store
                .read_nodes(from, (from + BLOCK).min(self.nodes))?,
        );
        let mut recent = lock();
        if recent.len() >= BLOCK_CACHE {
            recent.pop_front();
        }
        recent.push_back((b, nodes.clone()));
        Ok(nodes)
    }
}

/// The manifest as clients see it: the store's, with the input named by its file name only (the
/// path `prepare` was given says where files lie on the server, which is none of a client's
/// business) and only the files a client fetches listed.
pub fn served_manifest(m: &Manifest) -> Manifest {
    let mut served = m.clone();
    if let Some(name) = std::path::Path::new(&m.source).file_name() {
        served.source = name.to_string_lossy().into_owned();
    }
    // a client fetches the level-set band; the other files' sums are the server's to check, and
    // would cost every session about 90 bytes
    served.files.retain(|name, _| name == LEVELSET_BAND_FILE);
    served
}
