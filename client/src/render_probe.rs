//! Rendering inside `tetwave-bench progressive` (`--render-every K`): the leaf mesh of every K-th
//! step (and of the last) is drawn, timed, and compared with the CPU reference image of the
//! full-resolution mesh seen from the same camera, so that the thesis' FPS column comes with an
//! image error. The reference images depend on the step's camera only, so one set serves every
//! tolerance of a bench run.

use serde::Serialize;
use std::collections::HashMap;
use std::time::Instant;
use tetwave_adaptive::mesh::AdaptiveMesh;
use tetwave_gpu::pt::PtRenderer;
use tetwave_gpu::{GpuContext, RenderError};
use tetwave_protocol::view::Camera;
use tetwave_render::image_metrics::{psnr, Rgba8Image};
use tetwave_render::reference::render_reference;
use tetwave_render::render_mesh::RenderMesh;
use tetwave_render::transfer::TransferFunction;

/// What draws the sampled frames.
enum Drawer {
    /// Projected tetrahedra (wgpu), centroid order, as the streaming client draws.
    Gpu(Box<(GpuContext, PtRenderer)>),
    /// The CPU reference integrator.
    Cpu,
}

/// One sampled frame.
#[derive(Debug, Clone, Serialize)]
pub struct ProbeFrame {
    pub step: usize,
    pub tets: usize,
    /// Leaf mesh to image: conversion, upload and draw.
    pub ms: f64,
    /// The draw alone (GPU: visibility sort + draw + readback; CPU: the integration).
    pub draw_ms: f64,
    /// Against the CPU reference of the full-resolution mesh from the same camera (capped at 99).
    pub psnr_db: f64,
}

/// The rendering figures of one run.
#[derive(Debug, Clone, Serialize)]
pub struct RenderSummary {
    pub renderer: String,
    pub frames: Vec<ProbeFrame>,
    pub avg_ms: f64,
    pub max_ms: f64,
    pub avg_draw_ms: f64,
    pub avg_psnr_db: f64,
    pub min_psnr_db: f64,
}

/// Draws sampled steps of progressive runs and measures them (see the module docs).
pub struct RenderProbe {
    drawer: Drawer,
    tf: TransferFunction,
    /// The full-resolution mesh (every detail applied, uniform finest level).
    full: RenderMesh,
    value_range: [f32; 2],
    every: usize,
    /// Reference images by step, with the camera they were drawn from.
    references: HashMap<usize, (Camera, Rgba8Image)>,
    frames: Vec<ProbeFrame>,
    error: Option<RenderError>,
}

impl RenderProbe {
    /// A probe drawing every `every`-th step (at least 1) on the GPU, or with the CPU reference
    /// integrator when `cpu`; every image, `full`'s included, maps `value_range` (the dataset's)
    /// through the transfer function. Fails when a GPU is asked for and none can be opened.
    pub fn new(
        mut full: RenderMesh,
        value_range: [f32; 2],
        every: usize,
        cpu: bool,
        tf: TransferFunction,
    ) -> Result<Self, RenderError> {
        full.value_range = (value_range[0], value_range[1]);
        let drawer = if cpu {
            Drawer::Cpu
        } else {
            let ctx = GpuContext::new()?;
            let pt = PtRenderer::new(&ctx);
            pt.warm_up(&ctx, &tf)?;
            Drawer::Gpu(Box::new((ctx, pt)))
        };
        Ok(RenderProbe {
            drawer,
            tf,
            full,
            value_range,
            every: every.max(1),
            references: HashMap::new(),
            frames: Vec::new(),
            error: None,
        })
    }

    /// The renderer's name (with the adapter's, on the GPU).
    pub fn renderer(&self) -> String {
        match &self.drawer {
            Drawer::Gpu(g) => format!("gpu-pt {}", g.0.describe()),
            Drawer::Cpu => "cpu-reference".into(),
        }
    }

    /// Whether step `step` of `steps` is drawn: every `every`-th, and the last.
    pub fn wants(&self, step: usize, steps: usize) -> bool {
        step.is_multiple_of(self.every) || step + 1 == steps
    }

    /// Draws `mesh` as seen by `cam` at step `step` and records its time and PSNR. After an
    /// error, nothing more is drawn; [`Self::finish`] returns it.
    pub fn observe(&mut self, step: usize, mesh: &AdaptiveMesh, cam: &Camera) {
        if self.error.is_some() {
            return;
        }
        if let Err(e) = self.draw(step, mesh, cam) {
            self.error = Some(e);
        }
    }

    fn draw(&mut self, step: usize, mesh: &AdaptiveMesh, cam: &Camera) -> Result<(), RenderError> {
        let t = Instant::now();
        let rm = tetwave_adaptive::draw::leaf_mesh(mesh, self.value_range, None);
        let (img, draw_ms) = match &self.drawer {
            Drawer::Gpu(g) => {
                let (ctx, pt) = &**g;
                let data = pt.upload(ctx, &rm)?;
                let (img, times) = pt.render(ctx, &data, cam, &self.tf)?;
                (img, times.total_ms)
            }
            Drawer::Cpu => {
                let t = Instant::now();
                let img = render_reference(&rm, cam, &self.tf);
                (img, t.elapsed().as_secs_f64() * 1e3)
            }
        };
        let ms = t.elapsed().as_secs_f64() * 1e3;
        if self.references.get(&step).is_none_or(|(c, _)| c != cam) {
            let img = render_reference(&self.full, cam, &self.tf);
            self.references.insert(step, (*cam, img));
        }
        let reference = &self.references[&step].1;
        self.frames.push(ProbeFrame {
            step,
            tets: rm.tets.len(),
            ms,
            draw_ms,
            psnr_db: psnr(&img, reference).min(99.0),
        });
        Ok(())
    }

    /// The figures of the frames drawn since the last call (one run), or the first error.
    pub fn finish(&mut self) -> Result<RenderSummary, RenderError> {
        if let Some(e) = self.error.take() {
            self.frames.clear();
            return Err(e);
        }
        let frames = std::mem::take(&mut self.frames);
        let n = frames.len().max(1) as f64;
        Ok(RenderSummary {
            renderer: self.renderer(),
            avg_ms: frames.iter().map(|f| f.ms).sum::<f64>() / n,
            max_ms: frames.iter().map(|f| f.ms).fold(0.0, f64::max),
            avg_draw_ms: frames.iter().map(|f| f.draw_ms).sum::<f64>() / n,
            avg_psnr_db: frames.iter().map(|f| f.psnr_db).sum::<f64>() / n,
            min_psnr_db: frames
                .iter()
                .map(|f| f.psnr_db)
                .fold(f64::INFINITY, f64::min),
            frames,
        })
    }
}
