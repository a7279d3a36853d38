//! What the viewer shows: a stream from a server (the network on its own thread, through the
//! streaming client's network task), a local store fed to the same [`Session`] a chunk at a time,
//! or a mesh file drawn as it is. Each frame takes what has arrived within a time budget, so the
//! window never waits on the network or on a large arrival.

use crate::ingest::{Ingest, Step};
use crate::select::{SelectParams, Tolerance};
use crate::select_args::SelectionArgs;
use crate::session::Session;
use crate::stream::{
    network, ws_url, Delivery, Faults, Net, NetPolicy, NetRuntime, StreamError, INGEST_QUEUE,
};
use glam::DVec3;
use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tetwave_protocol::store_format::Manifest;
use tetwave_protocol::view::Camera;
use tetwave_protocol::wire::{ClientMsg, ViewParams};
use tetwave_protocol::{BaseMesh, DetailNode};
use tetwave_render::render_mesh::RenderMesh;
use tetwave_render::transfer::TransferFunction;
use tokio::sync::mpsc;

/// How the viewer's session selects: the command line's selection options (criterion, leaf
/// budget) and the transfer function drawn, which the image criterion weighs by.
#[derive(Debug, Clone)]
pub struct Selection {
    pub args: SelectionArgs,
    pub tf: TransferFunction,
}

impl Selection {
    /// The parameters of a session on `base` at tolerance `tol`, over `value_range`.
    fn params(&self, tol: Tolerance, value_range: [f32; 2], base: &BaseMesh) -> SelectParams {
        let mut p = SelectParams::new(tol, value_range);
        self.args.apply(&mut p, &self.tf, value_range, base);
        p
    }
}

/// What `tetwave view` was given.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Source {
    /// `http://host:port` or `ws://host:port` of a `tetwave-server serve`.
    Url(String),
    /// A store directory.
    Store(PathBuf),
    /// A mesh file (`.vtu`, `.vtk`, `.msh`, `.mesh`), drawn as it is.
    Mesh(PathBuf),
}

impl Source {
    pub fn parse(s: &str) -> Source {
        if s.starts_with("http://") || s.starts_with("ws://") {
            Source::Url(s.to_string())
        } else if crate::render_cli::is_mesh_input(Path::new(s), None) {
            Source::Mesh(s.into())
        } else {
            Source::Store(s.into())
        }
    }
}

/// Nodes of a local store fed to the session per chunk (the clock is read between chunks).
const LOCAL_CHUNK: usize = 512;

/// Reconnect attempts without progress before a lost stream counts as failed: with the network
/// task's linear backoff (100 ms more per attempt) about 19 s of trying, long enough for a
/// server to restart.
const RECONNECT_ATTEMPTS: u32 = 20;

struct Remote {
    /// The runtime whose one worker runs the network task (dropped with the viewer).
    rt: NetRuntime,
    task: tokio::task::JoinHandle<Result<(), StreamError>>,
    rx: mpsc::Receiver<(Delivery, u64)>,
    out: mpsc::UnboundedSender<ClientMsg>,
    net: Arc<Net>,
    ingest: Ingest,
    last_view: Option<ViewParams>,
    /// Reconnections when the view was last sent (a new connection needs it again).
    view_reconnects: u64,
    /// The server's HTTP address (`http://host:port`), for `/v1/render`.
    http: String,
}

enum Kind {
    Remote(Box<Remote>),
    Local { nodes: Vec<DetailNode>, next: usize },
    Mesh,
}

/// The data behind the view.
pub struct Data {
    kind: Kind,
    pub session: Option<Session>,
    /// A mesh file's mesh (no session).
    pub mesh: Option<RenderMesh>,
    /// The value range mapped to the transfer function (a store's
    /// [`display_value_range`](tetwave_protocol::store_format::Manifest::display_value_range)).
    pub value_range: [f32; 2],
    /// Centre and diagonal of the dataset's bounding box, once known.
    pub frame: Option<(DVec3, f64)>,
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
    select: Selection,
}

impl Data {
    /// Opens a source: a store or mesh file is read now; a stream connects on its own thread
    /// (`tf_auto`: it draws with `auto`, and asks the server for view order under it).
    pub fn open(
        source: &Source,
        token: Option<String>,
        tol: Tolerance,
        max_nodes: u64,
        select: Selection,
        tf_auto: bool,
    ) -> Result<Data, String> {
        let empty = |kind| Data {
            kind,
            session: None,
            mesh: None,
            value_range: [0.0, 1.0],
            frame: None,
            bytes_applied: 0,
            error: None,
            changed: true,
            levels: 0,
            name: String::new(),
            select: select.clone(),
        };
        match source {
            Source::Url(url) => {
                let ws = ws_url(url).map_err(|e| e.to_string())?;
                let http = format!(
                    "http://{}",
                    ws.trim_start_matches("ws://")
                        .trim_end_matches("/v1/stream")
                );
                let rt = NetRuntime::new("tetwave-view-net")
                    .map_err(|e| format!("network runtime: {e}"))?;
                let net = Arc::new(Net::new());
                let (tx, rx) = mpsc::channel(INGEST_QUEUE);
                let (out, out_rx) = mpsc::unbounded_channel();
                let task = rt.spawn(network(
                    ws,
                    token,
                    net.clone(),
                    tx,
                    out_rx,
                    NetPolicy {
                        faults: Faults::default(),
                        retries: RECONNECT_ATTEMPTS,
                        max_nodes,
                        tf_auto,
                    },
                ));
                Ok(empty(Kind::Remote(Box::new(Remote {
                    rt,
                    task,
                    rx,
                    out,
                    net,
                    ingest: Ingest::new(max_nodes),
                    last_view: None,
                    view_reconnects: 0,
                    http,
                }))))
            }
            Source::Store(dir) => {
                let store = tetwave_store::Store::open(dir).map_err(|e| e.to_string())?;
                let m = &store.manifest;
                let nodes = store
                    .read_nodes(0, m.counts.nodes)
                    .map_err(|e| e.to_string())?;
                let mut d = empty(Kind::Local { nodes, next: 0 });
                d.value_range = m.display_value_range();
                d.name = m.dataset.clone();
                d.start_session(store.base.clone(), tol)?;
                if let (Some(s), Some((_, near))) = (
                    d.session.as_mut(),
                    store.read_levelset_near().map_err(|e| e.to_string())?,
                ) {
                    s.set_levelset(near);
                }
                Ok(d)
            }
            Source::Mesh(path) => {
                let options = tetwave_import::clean::ImportOptions {
                    scalar: None,
                    field: None,
                    nan_as: None,
                };
                let (mesh, scalar) = crate::render_cli::file_mesh(path, None, &options)
                    .map_err(|e| e.to_string())?;
                let mut d = empty(Kind::Mesh);
                d.name = scalar;
                d.value_range = [mesh.value_range.0, mesh.value_range.1];
                d.frame = Some((mesh.center(), mesh.diagonal()));
                d.mesh = Some(mesh);
                Ok(d)
            }
        }
    }

    fn start_session(&mut self, base: BaseMesh, tol: Tolerance) -> Result<(), String> {
        let params = self.select.params(tol, self.value_range, &base);
        self.session = Some(Session::new(base, params).map_err(|e| format!("base mesh: {e}"))?);
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
        let (lo, hi) = (DVec3::from_array(lo), DVec3::from_array(hi));
        self.frame = Some(((lo + hi) * 0.5, hi.distance(lo)));
        self.levels = base.levels;
        self.changed = true;
    }

    /// Why drawn meshes are not clipped to the store's level set when it has one (its band could
    /// not be had); shown in the panel.
    pub fn levelset_error(&self) -> Option<&str> {
        match &self.kind {
            Kind::Remote(r) => r.ingest.levelset_error(),
            _ => None,
        }
    }

    /// A stream's manifest, once its session has started.
    pub fn remote_manifest(&self) -> Option<&Manifest> {
        match &self.kind {
            Kind::Remote(r) => r.ingest.manifest(),
            _ => None,
        }
    }

    /// The server's HTTP address, for a stream.
    pub fn server(&self) -> Option<&str> {
        match &self.kind {
            Kind::Remote(r) => Some(&r.http),
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
            Kind::Remote(r) => r.net.bytes.load(Ordering::Relaxed),
            _ => 0,
        }
    }

    /// Connections lost and retried so far (a stream; 0 otherwise).
    pub fn reconnects(&self) -> u64 {
        match &self.kind {
            Kind::Remote(r) => r.net.reconnects.load(Ordering::Relaxed),
            _ => 0,
        }
    }

    /// A stream whose connection was lost and is being retried (not yet complete, not failed).
    pub fn reconnecting(&self) -> bool {
        match &self.kind {
            Kind::Remote(r) => {
                self.error.is_none()
                    && !self.is_complete()
                    && r.net.reconnects.load(Ordering::Relaxed) > 0
                    && !r.net.connected.load(Ordering::Relaxed)
            }
            _ => false,
        }
    }

    /// Whether nodes were applied since the last call.
    pub fn take_changed(&mut self) -> bool {
        std::mem::take(&mut self.changed)
    }

    /// Tells the server the view (a stream only; sent when it changed, and again to a new
    /// connection after one was lost).
    pub fn send_view(&mut self, cam: &Camera, tol_px: f64) {
        if let Kind::Remote(r) = &mut self.kind {
            let view = cam.view_params(tol_px);
            let reconnects = r.net.reconnects.load(Ordering::Relaxed);
            if reconnects != r.view_reconnects {
                r.view_reconnects = reconnects;
                r.last_view = None;
            }
            if r.last_view != Some(view) {
                let _ = r.out.send(ClientMsg::View(view));
                r.last_view = Some(view);
            }
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
            Kind::Remote(_) => match self.ingest_remote(t0, budget, tol) {
                Ok(n) => applied = n,
                Err(e) => self.error = Some(e),
            },
        }
        if applied > 0 {
            self.changed = true;
        }
        applied
    }

    fn ingest_remote(
        &mut self,
        t0: Instant,
        budget: Duration,
        tol: Tolerance,
    ) -> Result<usize, String> {
        let mut applied = 0;
        loop {
            let Kind::Remote(r) = &mut self.kind else {
                unreachable!("remote")
            };
            if t0.elapsed() >= budget {
                return Ok(applied);
            }
            let (msg, nbytes) = match r.rx.try_recv() {
                Ok(m) => m,
                Err(mpsc::error::TryRecvError::Empty) => return Ok(applied),
                Err(mpsc::error::TryRecvError::Disconnected) => {
                    r.ingest.network_ended();
                    if self.session.as_ref().is_some_and(Session::is_complete) {
                        return Ok(applied);
                    }
                    // the network task ended: why (it has finished, so this does not wait)
                    let why = r.rt.block_on(&mut r.task);
                    return Err(match why {
                        Ok(Err(e)) => e.to_string(),
                        Ok(Ok(())) => "the network task ended".into(),
                        Err(e) => format!("the network task failed: {e}"),
                    });
                }
            };
            self.bytes_applied += nbytes;
            let select = &self.select;
            let start = |b: BaseMesh, m: &Manifest| {
                let params = select.params(tol, m.display_value_range(), &b);
                Session::new(b, params)
                    .map_err(|e| StreamError::Protocol(format!("base mesh: {e}")))
            };
            let step = r
                .ingest
                .apply(msg, &mut self.session, start, &r.out)
                .map_err(|e| e.to_string())?;
            match step {
                Step::Manifest => {
                    if let Some(m) = r.ingest.manifest() {
                        self.value_range = m.display_value_range();
                        self.name = m.dataset.clone();
                    }
                }
                Step::Started => self.session_started(),
                Step::LevelSet => self.changed = true,
                Step::Nodes { nodes, .. } => applied += nodes.len(),
                Step::Preview { nodes, .. } => applied += nodes,
                Step::End | Step::Nothing => {}
            }
        }
    }

    /// Stops the network task (the viewer is closing).
    pub fn close(&mut self) {
        if let Kind::Remote(r) = &mut self.kind {
            r.task.abort();
        }
    }
}
