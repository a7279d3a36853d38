//! # tetwave-source
//!
//! The data-source seam: what a user names ([`Source`]: a server's URL, a store directory, a mesh
//! file) and, once opened, the [`Data`] that feeds a [`Session`] within a time budget: a stream
//! through a [`tetwave_net::Connection`], a local store a chunk at a time, or a mesh file drawn as
//! it is (no session). Each call takes what has arrived within its budget, so a frame loop never
//! waits on the network or on a large arrival. [`load`] reads what a source holds at once (a
//! store's level, a mesh file, the histogram `auto` is fitted to).
//!
//! A new kind of source (e.g. a store read directly from object storage) is a new [`Source`]
//! variant and a new way for [`Data`] to feed the session. [`options`] are the option groups
//! every client command shares (camera, selection, image size).

pub mod load;
pub mod options;

use crate::options::SelectionArgs;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};
use tetwave_adaptive::select::{SelectParams, Tolerance};
use tetwave_adaptive::session::Session;
use tetwave_net::connection::{NetPolicy, Next};
use tetwave_net::ingest::{Ingest, Step};
use tetwave_net::transport::{Faulty, WebSocket};
use tetwave_net::{Connection, Faults, HttpError, NetError, ServerUrl};
use tetwave_protocol::store_format::Manifest;
use tetwave_protocol::view::{Camera, Framing};
use tetwave_protocol::{BaseMesh, DetailNode};
use tetwave_render::render_mesh::RenderMesh;
use tetwave_render::transfer::{TransferFunction, AUTO};

/// How a source's session selects: the command line's selection options (criterion, leaf
/// budget) and the transfer function drawn, which the image criterion weighs by.
#[derive(Debug, Clone)]
pub struct Selection {
    pub args: SelectionArgs,
    pub tf: TransferFunction,
    /// The function drawn is `auto`: a stream's session selects by it fitted to the manifest's
    /// histogram ([`TransferFunction::for_manifest`]) from its start.
    pub fit_auto: bool,
}

impl Selection {
    /// The parameters of a session on `base` at tolerance `tol`, over `value_range`.
    fn params(&self, tol: Tolerance, value_range: [f32; 2], base: &BaseMesh) -> SelectParams {
        let mut p = SelectParams::new(tol, value_range);
        self.args.apply(&mut p, &self.tf, value_range, base);
        p
    }
}

/// Why a source could not be opened or stopped feeding the session.
#[derive(Debug, thiserror::Error)]
pub enum SourceError {
    #[error(transparent)]
    Net(#[from] NetError),
    #[error(transparent)]
    Store(#[from] tetwave_store::StoreError),
    #[error(transparent)]
    Load(#[from] load::LoadError),
    #[error("base mesh: {0}")]
    BaseMesh(#[from] tetwave_adaptive::mesh::MeshError),
    #[error(transparent)]
    Node(#[from] tetwave_adaptive::session::NodeRejected),
    #[error("the store has {nodes} nodes, more than --max-nodes {max}")]
    TooLarge { nodes: u64, max: u64 },
    #[error("the transfer function: {0}")]
    Fit(String),
}

/// What `tetwave view` was given.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Source {
    /// `http://host:port` or `ws://host:port` of a `tetwave-server serve`.
    Url(String),
    /// A store directory.
    Store(PathBuf),
    /// A store in object storage read directly, no server: `s3://BUCKET/PREFIX`, or a folder
    /// over HTTP(S) (`https://…`, or `http://HOST/PATH` with a path that is not a server's
    /// route); blocks fetched by range as the session's selection asks for them.
    Bucket(tetwave_store::Location),
    /// A mesh file (`.vtu`, `.vtk`, `.msh`, `.mesh`) or a volume file or folder (NIfTI, NRRD,
    /// VTK image data, TIFF, DICOM, Zarr), drawn as it is.
    Mesh(PathBuf),
}

impl Source {
    /// What `s` names: a server is its root (`http://HOST:PORT`, `ws://…`, or a `/v1/…` route
    /// of one); `s3://…`, `https://…` and an `http://` URL with another path are stores read
    /// directly; anything else is a file or directory.
    pub fn parse(s: &str) -> Source {
        if let Some(loc) = bucket_location(s) {
            Source::Bucket(loc)
        } else if ServerUrl::is_server(s) {
            Source::Url(s.to_string())
        } else if load::is_mesh_input(Path::new(s), None) || load::is_volume_input(Path::new(s)) {
            Source::Mesh(s.into())
        } else {
            Source::Store(s.into())
        }
    }
}

/// The object-storage location `s` names, when it names a store read directly (see
/// [`Source::parse`]).
fn bucket_location(s: &str) -> Option<tetwave_store::Location> {
    let path = s.strip_prefix("http://").map(|rest| {
        let p = rest.find('/').map_or("", |i| &rest[i..]);
        p.split(['?', '#']).next().unwrap_or("")
    });
    let server = matches!(path, Some(p) if p.is_empty() || p == "/" || p.starts_with("/v1/"));
    if server || !(s.starts_with("s3://") || s.starts_with("https://") || s.starts_with("http://"))
    {
        return None;
    }
    tetwave_store::Location::parse(s).ok()
}

/// Blocks a store read directly fetches at most per round (one round trip: their ranges go
/// out together); 64 blocks are about 256 K nodes.
pub const FETCH_BLOCKS: usize = 64;

/// Nodes of a local store fed to the session per chunk (the clock is read between chunks).
const LOCAL_CHUNK: usize = 512;

/// Reconnect attempts without progress before a lost stream counts as failed, by default: with
/// the network task's linear backoff (100 ms more per attempt) about 19 s of trying, long enough
/// for a server to restart.
pub const RECONNECT_ATTEMPTS: u32 = 20;

/// How a source is opened.
#[derive(Debug, Clone)]
pub struct OpenOptions {
    /// The server's token, for a stream.
    pub token: Option<String>,
    /// The tolerance a store's session starts with.
    pub tol: Tolerance,
    /// The largest hierarchy accepted, in nodes (`--max-nodes`).
    pub max_nodes: u64,
    /// Reconnect attempts without progress (a stream).
    pub retries: u32,
    /// Transport faults to inject into a stream (tests); none by default.
    pub faults: Faults,
}

/// How one [`Data::pump`] takes a stream's deliveries.
#[derive(Debug, Clone, Copy)]
pub struct Pump {
    /// Stop taking deliveries once this instant has passed (checked after each, once a session
    /// exists).
    pub until: Instant,
    /// Wait, up to `until`, for a delivery when none has come in this call and more may come
    /// (always before the session starts); else take only what is queued.
    pub wait: bool,
    /// Stop after this many nodes (0: no limit).
    pub max_nodes: usize,
    /// Stop as soon as a session exists (its first frame goes out at once).
    pub stop_once_started: bool,
}

impl Pump {
    /// Take what is queued for at most `budget`, never waiting (a window's frame).
    pub fn within(budget: Duration) -> Pump {
        Pump {
            until: Instant::now() + budget,
            wait: false,
            max_nodes: 0,
            stop_once_started: false,
        }
    }
}

struct Remote {
    conn: Connection,
    ingest: Ingest,
}

/// A store read directly from object storage.
struct Bucket {
    store: std::sync::Arc<tetwave_store::PagedStore>,
    /// Blocks asked for (each once).
    fetched: std::collections::HashSet<u64>,
    /// Rounds to the reader thread, and what came of them: a window never waits on a request.
    ask: std::sync::mpsc::Sender<Vec<u64>>,
    got: std::sync::mpsc::Receiver<Result<Round, tetwave_store::StoreError>>,
    /// A round is under way.
    in_flight: bool,
}

/// A fetched round: each block with its nodes, and the bytes read for it.
type Round = (Vec<(u64, Vec<DetailNode>)>, u64);

impl Bucket {
    /// The store, with a thread that reads the rounds it is asked for (it ends with the
    /// `Bucket`).
    fn new(store: tetwave_store::PagedStore) -> Bucket {
        let store = std::sync::Arc::new(store);
        let (ask, asked) = std::sync::mpsc::channel::<Vec<u64>>();
        let (tell, got) = std::sync::mpsc::channel();
        let reader = store.clone();
        std::thread::Builder::new()
            .name("tetwave-bucket".into())
            .spawn(move || {
                for blocks in asked {
                    let before = reader.bytes_read();
                    let r = reader.read_blocks(&blocks).map(|nodes| {
                        let bytes = reader.bytes_read() - before;
                        (blocks.into_iter().zip(nodes).collect(), bytes)
                    });
                    if tell.send(r).is_err() {
                        break;
                    }
                }
            })
            .expect("a thread for the bucket's reads");
        Bucket {
            store,
            fetched: Default::default(),
            ask,
            got,
            in_flight: false,
        }
    }
}

enum Kind {
    Remote(Box<Remote>),
    Bucket(Box<Bucket>),
    Local { nodes: Vec<DetailNode>, next: usize },
    Mesh,
}

/// The data behind the view.
pub struct Data {
    kind: Kind,
    pub session: Option<Session>,
    /// A mesh file's mesh (no session).
    pub mesh: Option<RenderMesh>,
    /// A coarse proxy of [`Self::mesh`] that a viewer draws while the camera moves
    /// ([`load::motion_proxy`]; set by the viewer, which knows its budget).
    pub mesh_motion: Option<RenderMesh>,
    /// The value range mapped to the transfer function (a store's
    /// [`display_value_range`](tetwave_protocol::store_format::Manifest::display_value_range)).
    pub value_range: [f32; 2],
    /// Centre and diagonal of the dataset's bounding box, once known.
    pub frame: Option<Framing>,
    /// Wire bytes applied (remote), or 0.
    pub bytes_applied: u64,
    /// Why the data stopped (a failed connection, a refused node, …): shown, and the exit status.
    pub error: Option<String>,
    /// Nodes were applied since [`Self::take_changed`].
    changed: bool,
    /// Number of levels of the hierarchy (0 for a mesh file).
    pub levels: u8,
    /// What the legend names the scalar: a store's dataset (once its manifest is known), or a
    /// mesh file's scalar.
    pub name: String,
    /// The volume file's world, where the store (its manifest) or the file states one: the
    /// orientation axes are labelled with its anatomical directions.
    pub physical: Option<tetwave_store::Physical>,
    select: Selection,
}

impl Data {
    /// Opens a source: a store or mesh file is read now; a stream connects on its own thread
    /// (drawing `auto`, [`Selection::fit_auto`], it asks the server for view order under it).
    pub fn open(source: &Source, o: OpenOptions, select: Selection) -> Result<Data, SourceError> {
        let OpenOptions {
            token,
            tol,
            max_nodes,
            retries,
            faults,
        } = o;
        let tf_auto = select.fit_auto;
        let empty = |kind| Data {
            kind,
            session: None,
            mesh: None,
            mesh_motion: None,
            value_range: [0.0, 1.0],
            frame: None,
            bytes_applied: 0,
            error: None,
            changed: true,
            levels: 0,
            name: String::new(),
            physical: None,
            select: select.clone(),
        };
        match source {
            Source::Url(url) => {
                let server = ServerUrl::parse(url)?;
                let policy = NetPolicy {
                    retries,
                    max_nodes,
                    tf_auto,
                };
                let conn = if faults.none() {
                    Connection::open(server, token, policy, "tetwave-net")?
                } else {
                    let faulty = Faulty::new(WebSocket, faults);
                    Connection::open_with(faulty, server, token, policy, "tetwave-net")?
                };
                Ok(empty(Kind::Remote(Box::new(Remote {
                    conn,
                    ingest: Ingest::new(max_nodes),
                }))))
            }
            Source::Store(dir) => {
                let store = tetwave_store::Store::open(dir)?;
                let m = &store.manifest;
                let nodes = store.read_nodes(0, m.counts.nodes)?;
                let mut d = empty(Kind::Local { nodes, next: 0 });
                d.value_range = m.display_value_range();
                d.name = m.legend_name();
                d.physical = m.physical.clone();
                d.start_session(store.base.clone(), tol)?;
                if let (Some(s), Some((_, near))) =
                    (d.session.as_mut(), store.read_levelset_near()?)
                {
                    s.set_levelset(near);
                }
                Ok(d)
            }
            Source::Bucket(loc) => {
                let store = tetwave_store::PagedStore::open(loc)?;
                let m = store.manifest();
                if m.counts.nodes > max_nodes {
                    return Err(SourceError::TooLarge {
                        nodes: m.counts.nodes,
                        max: max_nodes,
                    });
                }
                let (range, name) = (m.display_value_range(), m.legend_name());
                let physical = m.physical.clone();
                let (base, near) = (store.base().clone(), store.levelset_near.clone());
                let opened = store.bytes_read();
                let mut d = empty(Kind::Bucket(Box::new(Bucket::new(store))));
                d.value_range = range;
                d.name = name;
                d.physical = physical;
                // the manifest, base mesh and first index page count as a stream's first frames do
                d.bytes_applied = opened;
                if d.select.fit_auto {
                    if let Kind::Bucket(b) = &d.kind {
                        d.select.tf = TransferFunction::for_manifest(AUTO, b.store.manifest())
                            .map_err(|e| SourceError::Fit(e.to_string()))?;
                    }
                }
                d.start_session(base, tol)?;
                if let (Some(s), Some(near)) = (d.session.as_mut(), near) {
                    s.set_levelset(near);
                }
                Ok(d)
            }
            Source::Mesh(path) => {
                let (mesh, name, physical) = load::drawn_file(path)?;
                let mut d = empty(Kind::Mesh);
                d.name = name;
                d.physical = physical;
                d.value_range = [mesh.value_range.0, mesh.value_range.1];
                let (lo, hi) = mesh.bounds();
                d.frame = Some(Camera::framing(lo.to_array(), hi.to_array()));
                d.mesh = Some(mesh);
                Ok(d)
            }
        }
    }

    fn start_session(&mut self, base: BaseMesh, tol: Tolerance) -> Result<(), SourceError> {
        let params = self.select.params(tol, self.value_range, &base);
        self.session = Some(Session::new(base, params)?);
        self.session_started();
        Ok(())
    }

    /// Keeps the session's image criterion on `tf`, the transfer function drawn: another transfer
    /// function makes other details visible (the next frame looks at the whole mesh again).
    pub fn follow_tf(&mut self, tf: &TransferFunction) {
        if self.select.tf == *tf {
            return;
        }
        self.select.tf = tf.clone();
        if let Some(s) = self.session.as_mut() {
            let mut p = s.params().clone();
            self.select
                .args
                .apply(&mut p, tf, self.value_range, s.base());
            s.set_params(p);
        }
    }

    /// Frames the view on a new session's base mesh.
    fn session_started(&mut self) {
        let Some(base) = self.session.as_ref().map(Session::base) else {
            return;
        };
        let (lo, hi) = base.bounds();
        self.frame = Some(Camera::framing(lo, hi));
        self.levels = base.levels;
        self.changed = true;
    }

    /// Why drawn meshes are not clipped to the store's level set when it has one (its band could
    /// not be had); shown in the panel.
    pub fn levelset_error(&self) -> Option<&HttpError> {
        match &self.kind {
            Kind::Remote(r) => r.ingest.levelset_error(),
            _ => None,
        }
    }

    /// A stream's manifest, once its session has started.
    pub fn remote_manifest(&self) -> Option<&Manifest> {
        match &self.kind {
            Kind::Remote(r) => r.ingest.manifest(),
            Kind::Bucket(b) => Some(b.store.manifest()),
            _ => None,
        }
    }

    /// The server's address, for a stream.
    pub fn server(&self) -> Option<&ServerUrl> {
        match &self.kind {
            Kind::Remote(r) => Some(r.conn.server()),
            _ => None,
        }
    }

    /// The store has a level set and no answer about it has come yet (a script's `wait` waits
    /// for it too).
    pub fn awaiting_levelset(&self) -> bool {
        matches!(&self.kind, Kind::Remote(r) if r.ingest.levelset_pending())
    }

    /// Whether drawn meshes are clipped to the store's level set.
    pub fn clipped(&self) -> bool {
        self.session.as_ref().is_some_and(Session::has_levelset)
    }

    /// Nodes held and in total (a mesh file: 0 of 0).
    pub fn progress(&self) -> (u64, u64) {
        self.session.as_ref().map_or((0, 0), Session::progress)
    }

    /// Every node held (or a mesh file).
    pub fn is_complete(&self) -> bool {
        match &self.kind {
            Kind::Mesh => true,
            _ => self.session.as_ref().is_some_and(Session::is_complete),
        }
    }

    /// Bytes received over the wire (remote), or 0.
    pub fn bytes_received(&self) -> u64 {
        match &self.kind {
            Kind::Remote(r) => r.conn.bytes(),
            Kind::Bucket(b) => b.store.bytes_read(),
            _ => 0,
        }
    }

    /// Connections lost and retried so far (a stream; 0 otherwise).
    pub fn reconnects(&self) -> u64 {
        match &self.kind {
            Kind::Remote(r) => r.conn.reconnects(),
            _ => 0,
        }
    }

    /// A stream whose connection was lost and is being retried (not yet complete, not failed).
    pub fn reconnecting(&self) -> bool {
        match &self.kind {
            Kind::Remote(r) => {
                self.error.is_none()
                    && !self.is_complete()
                    && r.conn.reconnects() > 0
                    && !r.conn.connected()
            }
            _ => false,
        }
    }

    /// Whether nodes were applied since the last call.
    pub fn take_changed(&mut self) -> bool {
        std::mem::take(&mut self.changed)
    }

    /// Tells the server the view (a stream only; sent when it changed, and by the connection
    /// again to a new connection after one was lost).
    pub fn send_view(&mut self, cam: &Camera, tol_px: f64) {
        if let Kind::Remote(r) = &mut self.kind {
            r.conn.send_view(cam.view_params(tol_px));
        }
    }

    /// Applies what has arrived, for at most about `budget`. Returns the nodes applied.
    pub fn ingest(&mut self, budget: Duration, tol: Tolerance) -> usize {
        if self.error.is_some() {
            return 0;
        }
        let t0 = Instant::now();
        let mut applied = 0;
        match &mut self.kind {
            Kind::Mesh => {}
            Kind::Local { nodes, next } => {
                let session = self.session.as_mut().expect("a store has a session");
                while *next < nodes.len() && t0.elapsed() < budget {
                    let end = (*next + LOCAL_CHUNK).min(nodes.len());
                    if let Err(e) = session.insert(&nodes[*next..end]) {
                        self.error = Some(e.to_string());
                        break;
                    }
                    applied += end - *next;
                    *next = end;
                }
                if *next == nodes.len() {
                    // held by the session now
                    *nodes = Vec::new();
                    *next = 0;
                }
            }
            Kind::Remote(_) | Kind::Bucket(_) => match self.pump(Pump::within(budget), tol, |_| {})
            {
                Ok(n) => applied = n,
                Err(e) => self.error = Some(e.to_string()),
            },
        }
        if applied > 0 {
            self.changed = true;
        }
        applied
    }

    /// Takes a stream's deliveries as `p` says and applies them (a session is built on the base
    /// mesh with tolerance `tol`); each step goes to `on` after the data has taken what it keeps.
    /// Returns the nodes applied (preview nodes included). An error ends the stream: before the
    /// session started, nothing is left to draw; after, the frames so far stand. Not a stream:
    /// nothing to take.
    pub fn pump(
        &mut self,
        p: Pump,
        tol: Tolerance,
        mut on: impl FnMut(Step),
    ) -> Result<usize, NetError> {
        if matches!(self.kind, Kind::Bucket(_)) {
            return self.fetch_round(p, on);
        }
        let mut applied = 0;
        let mut got_any = false;
        loop {
            let Kind::Remote(r) = &mut self.kind else {
                return Ok(applied);
            };
            if p.max_nodes > 0 && applied >= p.max_nodes {
                return Ok(applied);
            }
            // once everything has arrived there is nothing to wait for but the level set
            let more = !r.ingest.ended() || r.ingest.levelset_pending();
            let waiting = p.wait && (self.session.is_none() || (!got_any && more));
            let wait = if waiting {
                p.until.saturating_duration_since(Instant::now())
            } else {
                Duration::ZERO
            };
            let (msg, nbytes) = match r.conn.next(wait) {
                Next::Ready(d, n) => (d, n),
                Next::Empty => return Ok(applied),
                // a waiting pump that has taken what came draws it first; the next call, which
                // waits, says why the stream ended
                Next::Ended if p.wait && !waiting => return Ok(applied),
                Next::Ended => {
                    r.ingest.network_ended();
                    if self.session.as_ref().is_some_and(Session::is_complete) {
                        return Ok(applied);
                    }
                    // the network task ended: why (it has finished, so this does not wait)
                    return Err(r.conn.finish());
                }
            };
            got_any = true;
            self.bytes_applied += nbytes;
            let select = &self.select;
            let mut fitted = None;
            let start = |b: BaseMesh, m: &Manifest| {
                let mut sel = select.clone();
                if sel.fit_auto {
                    sel.tf = TransferFunction::for_manifest(AUTO, m)?;
                }
                let params = sel.params(tol, m.display_value_range(), &b);
                fitted = Some(sel.tf);
                Session::new(b, params).map_err(NetError::BaseMesh)
            };
            let step = r
                .ingest
                .apply(msg, &mut self.session, start, r.conn.sender())?;
            if let Some(tf) = fitted {
                self.select.tf = tf;
            }
            match &step {
                Step::Manifest => {
                    if let Some(m) = r.ingest.manifest() {
                        self.value_range = m.display_value_range();
                        self.name = m.legend_name();
                        self.physical = m.physical.clone();
                    }
                }
                Step::Started => self.session_started(),
                Step::LevelSet => self.changed = true,
                Step::Nodes { nodes, .. } => applied += nodes.len(),
                Step::Preview { nodes, .. } => applied += nodes,
                Step::End | Step::Nothing => {}
            }
            on(step);
            if self.session.is_some() && (p.stop_once_started || Instant::now() >= p.until) {
                return Ok(applied);
            }
        }
    }

    /// A store read directly: takes the round of blocks under way when it has come (waiting for
    /// it up to `p.until` when `p.wait` and nothing was applied yet), applying every node of it
    /// (each block is the store's own), then asks the reader thread for the next round: the
    /// blocks holding the nodes the session wants for its last frame's camera
    /// ([`Session::wanted`]), coarsest first, at most [`FETCH_BLOCKS`] (and `p.max_nodes` worth).
    fn fetch_round(&mut self, p: Pump, mut on: impl FnMut(Step)) -> Result<usize, NetError> {
        let (Kind::Bucket(b), Some(session)) = (&mut self.kind, self.session.as_mut()) else {
            return Ok(0);
        };
        let mut applied = 0;
        loop {
            if b.in_flight {
                let wait = match p.wait && applied == 0 {
                    true => p.until.saturating_duration_since(Instant::now()),
                    false => Duration::ZERO,
                };
                let round = match b.got.recv_timeout(wait) {
                    Ok(Ok(round)) => round,
                    Ok(Err(e)) => return Err(NetError::Store(e.to_string())),
                    Err(std::sync::mpsc::RecvTimeoutError::Timeout) => break,
                    Err(std::sync::mpsc::RecvTimeoutError::Disconnected) => {
                        return Err(NetError::Store("the store's reader thread stopped".into()))
                    }
                };
                b.in_flight = false;
                self.bytes_applied += round.1;
                for (_, nodes) in round.0 {
                    session
                        .insert(&nodes)
                        .map_err(|e| NetError::Store(e.to_string()))?;
                    applied += nodes.len();
                    on(Step::Nodes {
                        nodes,
                        duplicates: 0,
                    });
                }
            }
            let most = match p.max_nodes {
                0 => FETCH_BLOCKS,
                n => n
                    .div_ceil(tetwave_store::BLOCK as usize)
                    .clamp(1, FETCH_BLOCKS),
            };
            let mut blocks: Vec<u64> = session
                .wanted()
                .into_iter()
                .map(|id| id / tetwave_store::BLOCK)
                .filter(|blk| !b.fetched.contains(blk))
                .collect();
            blocks.sort_unstable();
            blocks.dedup();
            blocks.truncate(most);
            if blocks.is_empty() {
                break;
            }
            b.fetched.extend(blocks.iter().copied());
            b.ask
                .send(blocks)
                .map_err(|_| NetError::Store("the store's reader thread stopped".into()))?;
            b.in_flight = true;
            // one round applied a call: the frame uses it while the next is fetched
            if applied > 0 || !p.wait {
                break;
            }
        }
        if applied > 0 {
            self.changed = true;
        }
        Ok(applied)
    }

    /// The transfer function the session selects by (for a stream drawing `auto`, the one fitted
    /// to its manifest once the session started).
    pub fn selection_tf(&self) -> &TransferFunction {
        &self.select.tf
    }

    /// A stream whose server said every node was sent, and every node is held.
    pub fn stream_ended(&self) -> bool {
        match &self.kind {
            Kind::Remote(r) => r.ingest.ended(),
            Kind::Bucket(_) => self.is_complete(),
            _ => false,
        }
    }

    /// Stops the network task (the viewer is closing).
    pub fn close(&mut self) {
        if let Kind::Remote(r) = &mut self.kind {
            r.conn.close();
        }
    }
}
