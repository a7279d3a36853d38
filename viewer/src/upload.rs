//! Uploads leaf meshes off the frame loop. Building a mesh's draw data (face planes, gradients,
//! GPU buffers) takes tens of milliseconds at 10⁵ tets, more than a frame: the frame hands the
//! leaf mesh to this thread and keeps drawing the mesh before it, for the new camera, until the
//! new one is ready. A slow upload then shows as a coarser (older) mesh for a frame or two,
//! not as a frame that answers the mouse late.

use std::sync::mpsc;
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Instant;
use tetwave_gpu::pt::{PtRenderer, TetDrawData};
use tetwave_gpu::{GpuContext, RenderError};
use tetwave_render::render_mesh::RenderMesh;

/// An upload's result (the leaf mesh's draw data, and the coarser mesh's drawn in motion when
/// one was given) and how long it took, in milliseconds.
pub type Uploaded = (Result<(TetDrawData, Option<TetDrawData>), UploadError>, f64);

/// Why an upload failed.
#[derive(Debug, thiserror::Error)]
pub enum UploadError {
    #[error(transparent)]
    Render(#[from] RenderError),
    #[error("the upload thread has ended")]
    ThreadEnded,
}

/// What one upload takes: the leaf mesh, and the coarser one to draw in motion if any.
type Meshes = (RenderMesh, Option<RenderMesh>);

/// One upload at a time on a thread of its own.
pub struct Uploader {
    tx: Option<mpsc::Sender<Meshes>>,
    rx: mpsc::Receiver<Uploaded>,
    thread: Option<JoinHandle<()>>,
    in_flight: bool,
}

impl Uploader {
    pub fn new(gpu: Arc<GpuContext>, renderer: Arc<PtRenderer>) -> Uploader {
        let (tx, meshes) = mpsc::channel::<Meshes>();
        let (done, rx) = mpsc::channel();
        let thread = std::thread::Builder::new()
            .name("tetwave-view-upload".into())
            .spawn(move || {
                for (m, motion) in meshes {
                    let t = Instant::now();
                    let up = |m: &RenderMesh| renderer.upload(&gpu, m).map_err(UploadError::from);
                    let r = up(&m).and_then(|d| Ok((d, motion.as_ref().map(up).transpose()?)));
                    if done.send((r, t.elapsed().as_secs_f64() * 1e3)).is_err() {
                        break;
                    }
                }
            })
            .ok();
        Uploader {
            tx: Some(tx),
            rx,
            thread,
            in_flight: false,
        }
    }

    /// An upload is under way (its mesh is not drawn yet).
    pub fn busy(&self) -> bool {
        self.in_flight
    }

    /// Starts uploading `mesh` and the coarser `motion` mesh; only when not [`Self::busy`]. Fails
    /// if the thread is gone.
    pub fn start(
        &mut self,
        mesh: RenderMesh,
        motion: Option<RenderMesh>,
    ) -> Result<(), UploadError> {
        debug_assert!(!self.in_flight, "one upload at a time");
        let sent = self
            .tx
            .as_ref()
            .is_some_and(|tx| tx.send((mesh, motion)).is_ok());
        if !sent {
            return Err(UploadError::ThreadEnded);
        }
        self.in_flight = true;
        Ok(())
    }

    /// The finished upload, if the one under way is done.
    pub fn take(&mut self) -> Option<Uploaded> {
        if !self.in_flight {
            return None;
        }
        match self.rx.try_recv() {
            Ok(r) => {
                self.in_flight = false;
                Some(r)
            }
            Err(mpsc::TryRecvError::Empty) => None,
            Err(mpsc::TryRecvError::Disconnected) => {
                self.in_flight = false;
                Some((Err(UploadError::ThreadEnded), 0.0))
            }
        }
    }
}

impl Drop for Uploader {
    fn drop(&mut self) {
        // closing the channel ends the thread after its current upload
        self.tx = None;
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}
