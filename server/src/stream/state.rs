//! [`Shared`]: what every connection and request shares: the store (manifest, base mesh and block
//! index), the frames that never change, a bounded cache of decoded blocks, and the vertex values
//! of the first levels that view order ranks by ([`Coarse`]). Nothing here grows with the store's
//! node count: what a session needs beyond it, its schedule holds.

use super::admission::{Admission, PeerBudgets};
use super::auth::FailureLimiter;
use super::config::{ServeConfig, ViewCriterion, ViewTf};
use super::error::ServeError;
use super::walk::Coarse;
use crate::render_service::RenderService;
use axum::body::Bytes;
use std::collections::{BTreeMap, HashMap, HashSet};
use std::sync::atomic::{AtomicU64, Ordering as AtomicOrdering};
use std::sync::{Arc, Condvar, Mutex, OnceLock, Weak};
use tetwave_protocol::block::{BlockCoder, NodeBlock};
use tetwave_protocol::node::resolve_bound;
use tetwave_protocol::store_format::LEVELSET_BAND_FILE;
use tetwave_protocol::view::{ImageCriterion, DEFAULT_IMAGE_EPS};
use tetwave_protocol::wire::{encode, ServerMsg, SessionStart, ViewParams};
use tetwave_protocol::{DetailNode, Forest, TetId};
use tetwave_render::transfer::{TransferFunction, ValueHistogram};
use tetwave_store::Manifest;
use tetwave_store::{OpenOptions, Store, StoreError, BLOCK};

/// The transfer function streaming clients draw with by default.
fn default_tf() -> TransferFunction {
    TransferFunction::preset("default").expect("the default preset exists")
}

/// What every connection shares: the store, encoded frames that never change, a block cache.
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
    /// Decoded blocks, least recently used dropped first, within
    /// [`ServeConfig::cache_limit_bytes`].
    blocks: Mutex<BlockCache>,
    /// Signalled when a block being read lands in the cache (or its read fails).
    landed: Condvar,
    /// Block numbers to read ahead ([`Self::prefetch`]), for the [`PREFETCHERS`] threads.
    ahead: Mutex<Option<std::sync::mpsc::SyncSender<u64>>>,
    /// Blocks found in the cache, and read from the store (`/healthz`, `/metrics`).
    pub(super) block_hits: AtomicU64,
    pub(super) block_reads: AtomicU64,
    /// The store's preview and its coder, when it has one and new sessions get some of it
    /// ([`ServeConfig::preview_share`]).
    pub(super) preview: Option<ServedPreview>,
    /// The vertex values view order ranks the first levels by (built once, off the start).
    coarse: OnceLock<Arc<Coarse>>,
    /// The image criteria of `default` and `auto` (`None` under [`ViewCriterion::Data`]).
    criteria: [Option<ImageCriterion>; 2],
    pub(super) connections: AtomicU64,
    /// Walks started by view-order sessions (`/healthz` reports it as `view_rescans`).
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
    /// Batches being computed at once, at most one a core.
    pub(super) batch_slots: tokio::sync::Semaphore,
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

/// Decoded blocks by block number, with their estimated bytes and last use.
#[derive(Default)]
struct BlockCache {
    blocks: HashMap<u64, (Arc<Vec<DetailNode>>, u64, u64)>,
    /// Last use → block, oldest first.
    uses: BTreeMap<u64, u64>,
    bytes: u64,
    clock: u64,
    /// Blocks being read: a second reader waits for the first instead of asking again.
    reading: HashSet<u64>,
}

impl BlockCache {
    fn get(&mut self, b: u64) -> Option<Arc<Vec<DetailNode>>> {
        self.clock += 1;
        let (nodes, _, used) = self.blocks.get_mut(&b)?;
        self.uses.remove(used);
        *used = self.clock;
        self.uses.insert(self.clock, b);
        Some(nodes.clone())
    }

    /// Keeps `nodes` as block `b`, dropping the least recently used blocks while the cache would
    /// exceed `limit` bytes (a block larger than `limit` is not kept).
    fn put(&mut self, b: u64, nodes: Arc<Vec<DetailNode>>, limit: u64) {
        let bytes = nodes
            .iter()
            .map(|n| NODE_BYTES + 4 * n.coeffs.len() as u64)
            .sum::<u64>();
        if bytes > limit || self.blocks.contains_key(&b) {
            return;
        }
        while self.bytes + bytes > limit {
            let Some((_, old)) = self.uses.pop_first() else {
                break;
            };
            if let Some((_, n, _)) = self.blocks.remove(&old) {
                self.bytes -= n;
            }
        }
        self.clock += 1;
        self.uses.insert(self.clock, b);
        self.blocks.insert(b, (nodes, bytes, self.clock));
        self.bytes += bytes;
    }
}

/// Threads reading blocks ahead of the sessions that will ask for them, and blocks queued for them.
const PREFETCHERS: usize = 16;
const PREFETCH_QUEUE: usize = 1024;

/// A decoded node's memory besides its coefficients: the struct and its allocation's header.
const NODE_BYTES: u64 = std::mem::size_of::<DetailNode>() as u64 + 16;

impl Shared {
    /// Opens the store and prepares what connections share: the manifest, base mesh, block
    /// index and checksums, and the first block (the others are decoded, and checked against
    /// their checksums, when they are first read).
    pub fn open(dir: &std::path::Path, config: ServeConfig) -> Result<Arc<Shared>, ServeError> {
        let store = Store::open_with(
            dir,
            OpenOptions {
                verify_checksums: config.verify_checksums,
                lazy: true,
            },
        )?;
        Self::serve_store(store, config)
    }

    fn serve_store(mut store: Store, config: ServeConfig) -> Result<Arc<Shared>, ServeError> {
        let forest = store.forest();
        let nodes = store.manifest.counts.nodes;
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
        tracing::info!(nodes, "store {} opened for serving", store.location);
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
        let criteria = match config.view_criterion {
            ViewCriterion::Data => [None, None],
            ViewCriterion::Image => {
                let (range, base) = (store.manifest.value_range, &store.base);
                let tf = default_tf();
                let auto = ValueHistogram::of_manifest(&store.manifest)
                    .map_or_else(|| tf.clone(), |h| tf.fitted(&h));
                [
                    Some(tf.image_criterion(range, base, DEFAULT_IMAGE_EPS)),
                    Some(auto.image_criterion(range, base, DEFAULT_IMAGE_EPS)),
                ]
            }
        };
        let render = RenderService::new(&store.dir);
        let admission = Admission::new(config.limits.clone());
        let shared = Arc::new(Shared {
            store,
            config,
            forest,
            nodes,
            manifest_json,
            start_frame,
            base_frame,
            levelset_near,
            blocks: Mutex::new(BlockCache::default()),
            landed: Condvar::new(),
            ahead: Mutex::new(None),
            block_hits: AtomicU64::new(0),
            block_reads: AtomicU64::new(0),
            preview,
            coarse: OnceLock::new(),
            criteria,
            connections: AtomicU64::new(0),
            view_rescans: AtomicU64::new(0),
            render,
            admission,
            auth_failures: FailureLimiter::default(),
            budgets: PeerBudgets::default(),
            render_run: tokio::sync::Mutex::new(()),
            batch_slots: tokio::sync::Semaphore::new(
                std::thread::available_parallelism().map_or(2, |n| n.get()),
            ),
        });
        shared.start_prefetchers();
        // the coarsest nodes, which every session reads first: a store whose first block does
        // not decode (or fails its checksum) is refused here, not by its first client
        if shared.nodes > 0 {
            shared.block(0)?;
        }
        Ok(shared)
    }

    /// Number of detail nodes.
    pub fn nodes(&self) -> u64 {
        self.nodes
    }

    /// Open WebSocket connections.
    pub fn connections(&self) -> u64 {
        self.connections.load(AtomicOrdering::Relaxed)
    }

    /// Builds what view order reads (the coarse levels' vertex values) on a thread of its own, so that the first
    /// session in view order does not wait for it (a session that asks before it is done waits
    /// for the same computation, not a second one).
    pub fn warm_view_order(self: &Arc<Self>) {
        let s = Arc::clone(self);
        let spawned = std::thread::Builder::new()
            .name("view-order".into())
            .spawn(move || {
                s.coarse();
            });
        if let Err(e) = spawned {
            tracing::warn!("view order is prepared by the first session that needs it: {e}");
        }
    }

    /// Whether a session in the configured order starts at once: always, but in view order
    /// before its coarse values are built ([`Self::warm_view_order`]).
    pub(super) fn view_order_ready(&self) -> bool {
        self.config.order != super::config::Order::View || self.coarse.get().is_some()
    }

    /// The vertex values of the first levels (built at the first call).
    pub(super) fn coarse(&self) -> Arc<Coarse> {
        self.coarse
            .get_or_init(|| {
                let t0 = std::time::Instant::now();
                let c = Coarse::build(&self.store, self.config.coarse_nodes).unwrap_or_else(|e| {
                    tracing::warn!("view order ranks by the base mesh's values alone: {e}");
                    Coarse::base_only(&self.store)
                });
                tracing::info!(
                    levels = c.level(),
                    "view order's coarse values built in {:.2} s",
                    t0.elapsed().as_secs_f64()
                );
                Arc::new(c)
            })
            .clone()
    }

    /// The image criterion view order ranks a session drawing with `tf` by (`None`: data
    /// weights). Where the manifest has no histogram, `auto`'s is `default`'s, as the client's
    /// `auto` then is the preset.
    pub(super) fn criterion(&self, tf: ViewTf) -> Option<ImageCriterion> {
        self.criteria[(tf == ViewTf::Auto) as usize].clone()
    }

    /// Every node's view-order priority for `view` and a client drawing with `tf` (larger is
    /// sent first), each from its path down the hierarchy: for tests and small stores (it
    /// reads every block).
    pub fn view_priorities(&self, view: &ViewParams, tf: ViewTf) -> Result<Vec<f32>, StoreError> {
        self.priorities_of(view, self.criterion(tf), 0..self.nodes)
    }

    /// The camera view order follows until a session's first `View` (the render CLI's
    /// default).
    pub(super) fn default_view(&self) -> ViewParams {
        use tetwave_protocol::view::{Camera, Orbit};
        let (lo, hi) = self.store.base.bounds();
        let cam = Orbit::framed(Camera::framing(lo, hi)).camera(512, 512);
        ViewParams {
            eye: cam.eye.to_array(),
            target: cam.target.to_array(),
            up: [0.0, 0.0, 1.0],
            fovy_deg: cam.fovy_deg,
            width: cam.width,
            height: cam.height,
            tol_px: 1.0,
        }
    }

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

    /// Nodes `ids` (sorted in place), decoding each block they touch once.
    pub(super) fn fetch(&self, ids: &mut [TetId]) -> Result<Vec<DetailNode>, StoreError> {
        ids.sort_unstable();
        // every block after the first is asked for at once, and read while the first is
        let mut blocks: Vec<u64> = ids.iter().map(|i| i / BLOCK).collect();
        blocks.dedup();
        self.prefetch_blocks(blocks.into_iter().skip(1));
        let mut out = Vec::with_capacity(ids.len());
        self.each_node(ids.iter().copied(), |n| out.push(n.clone()))?;
        Ok(out)
    }

    /// The resolved subtree bounds of nodes `from..to` (a finest-level node's is its parent's,
    /// `parent`: every caller asks for one sibling group or base level at a time).
    pub(super) fn bounds(
        &self,
        from: TetId,
        to: TetId,
        parent: f32,
    ) -> Result<Vec<f32>, StoreError> {
        let mut out = Vec::with_capacity((to - from) as usize);
        self.each_node(from..to.min(self.nodes), |n| {
            out.push(resolve_bound(n.subtree_max_abs, || Some(parent)))
        })?;
        Ok(out)
    }

    /// Hands node `id` of each of `ids` (increasing) to `f`, a block at a time.
    fn each_node(
        &self,
        ids: impl Iterator<Item = TetId>,
        mut f: impl FnMut(&DetailNode),
    ) -> Result<(), StoreError> {
        let mut held: Option<(u64, Arc<Vec<DetailNode>>)> = None;
        for id in ids {
            let b = id / BLOCK;
            if held.as_ref().is_none_or(|(hb, _)| *hb != b) {
                held = Some((b, self.block(b)?));
            }
            let (_, block) = held.as_ref().expect("held");
            let node = block
                .get((id - b * BLOCK) as usize)
                .ok_or_else(|| StoreError::Corrupt {
                    path: self.store.dir.join("blocks.bin"),
                    reason: format!("node {id} is outside block {b}"),
                })?;
            f(node);
        }
        Ok(())
    }

    /// The decoded nodes of store block `b`, from the cache or the store (waiting for a read
    /// of it already under way).
    fn block(&self, b: u64) -> Result<Arc<Vec<DetailNode>>, StoreError> {
        let mut c = self.blocks.lock().unwrap_or_else(|e| e.into_inner());
        loop {
            if let Some(nodes) = c.get(b) {
                self.block_hits.fetch_add(1, AtomicOrdering::Relaxed);
                return Ok(nodes);
            }
            if !c.reading.contains(&b) {
                break;
            }
            c = self.landed.wait(c).unwrap_or_else(|e| e.into_inner());
        }
        c.reading.insert(b);
        drop(c);
        self.read_block(b)
    }

    /// Reads and decodes block `b` (marked as being read) into the cache, outside the lock.
    fn read_block(&self, b: u64) -> Result<Arc<Vec<DetailNode>>, StoreError> {
        self.block_reads.fetch_add(1, AtomicOrdering::Relaxed);
        let from = b * BLOCK;
        let read = self
            .store
            .read_nodes(from, (from + BLOCK).min(self.nodes))
            .map(Arc::new);
        let mut c = self.blocks.lock().unwrap_or_else(|e| e.into_inner());
        c.reading.remove(&b);
        if let Ok(nodes) = &read {
            c.put(b, nodes.clone(), self.config.cache_limit_bytes);
        }
        drop(c);
        self.landed.notify_all();
        read
    }

    /// Starts reading the blocks of nodes `from..to` that are neither held nor being read, on
    /// the read-ahead threads (a store in object storage answers each request after a round
    /// trip: reads that overlap cost one). Does nothing when the queue is full or the cache
    /// holds nothing.
    pub(super) fn prefetch(&self, from: TetId, to: TetId) {
        let to = to.min(self.nodes);
        if from < to {
            self.prefetch_blocks(from / BLOCK..=(to - 1) / BLOCK);
        }
    }

    /// [`Self::prefetch`] of whole blocks.
    fn prefetch_blocks(&self, blocks: impl IntoIterator<Item = u64>) {
        if self.config.cache_limit_bytes == 0 {
            return;
        }
        let ahead = self.ahead.lock().unwrap_or_else(|e| e.into_inner());
        let Some(tx) = ahead.as_ref() else {
            return;
        };
        let mut c = self.blocks.lock().unwrap_or_else(|e| e.into_inner());
        for b in blocks {
            if c.blocks.contains_key(&b) || c.reading.contains(&b) {
                continue;
            }
            if tx.try_send(b).is_err() {
                return;
            }
            c.reading.insert(b);
        }
    }

    /// Starts the [`PREFETCHERS`] read-ahead threads (they end with the last `Arc`).
    fn start_prefetchers(self: &Arc<Self>) {
        let (tx, rx) = std::sync::mpsc::sync_channel::<u64>(PREFETCH_QUEUE);
        let rx = Arc::new(Mutex::new(rx));
        for k in 0..PREFETCHERS {
            let (rx, weak): (_, Weak<Shared>) = (rx.clone(), Arc::downgrade(self));
            let spawned = std::thread::Builder::new()
                .name(format!("read-ahead-{k}"))
                .spawn(move || loop {
                    let next = rx.lock().unwrap_or_else(|e| e.into_inner()).recv();
                    let (Ok(b), Some(s)) = (next, weak.upgrade()) else {
                        return;
                    };
                    if let Err(e) = s.read_block(b) {
                        tracing::debug!("read-ahead of block {b}: {e}");
                    }
                });
            if let Err(e) = spawned {
                tracing::warn!("blocks are read without read-ahead: {e}");
                return;
            }
        }
        *self.ahead.lock().unwrap_or_else(|e| e.into_inner()) = Some(tx);
    }

    /// The decoded blocks held and their estimated bytes (`/healthz`).
    pub(super) fn cache_held(&self) -> (usize, u64) {
        let c = self.blocks.lock().unwrap_or_else(|e| e.into_inner());
        (c.blocks.len(), c.bytes)
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
