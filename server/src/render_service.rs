//! Fallback images for clients that cannot render: what `GET /v1/render` answers (a PNG of the
//! store's uniform level, drawn with the client library's renderer: projected tetrahedra on the GPU
//! when an adapter exists, the CPU reference integrator otherwise) and `GET /` shows (a small page
//! that shows them, with orbit by mouse drag and a tolerance slider; no external resources). The
//! routes themselves are [`crate::stream`]'s; this module knows nothing of them.
//!
//! Query parameters of `/v1/render` (all optional): `width`, `height` (1..=4096, default 512),
//! `azimuth`, `elevation` (degrees, finite, default 35 / 25; elevation within ±90), `distance`
//! (> 0, default 1.6 × the bounding-box diagonal), `fov` (degrees in `[1, 179]`, default 40),
//! `tol` (screen-space tolerance in pixels, ≥ 0: the coarsest uniform level whose tets project to at
//! most `tol` pixels; 0 = finest) or `level` (≤ the store's levels; default finest), `tf` (a preset:
//! default, transparent, opaque, shells), `renderer` (`auto`, `gpu`, `cpu`). Anything else, or a value
//! out of range, is a 400 with a message. The answer carries `X-Tetwave-Renderer`,
//! `X-Tetwave-Level` and `X-Tetwave-Tets` headers.
//!
//! The image maps the manifest's default value range (the input's, when `prepare` recorded it) and
//! is clipped to the store's level set (`levelset.f32`) when it has one, so that it is the image
//! `tetwave render <store>` draws for the same view.

use axum::http::StatusCode;
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use tetwave_gpu::pt::{PtRenderer, TetDrawData};
use tetwave_gpu::{GpuContext, RenderError};
use tetwave_protocol::store_format::Manifest;
use tetwave_protocol::view::{Camera, Orbit};
use tetwave_protocol::BaseMesh;
use tetwave_render::image_metrics::Rgba8Image;
use tetwave_render::reference::render_reference_cancellable;
use tetwave_render::render_mesh::RenderMesh;
use tetwave_render::transfer::TransferFunction;
use tetwave_store::Store;

/// Largest image side.
pub const MAX_SIDE: u32 = 4096;
/// Transfer functions `/v1/render` accepts (never a file path): `auto` (the default preset fitted
/// to the store's value histogram, as every client fits it) and the presets.
pub const TF_PRESETS: [&str; 5] = ["auto", "default", "transparent", "opaque", "shells"];

/// Which renderer a request asks for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RendererChoice {
    /// GPU when an adapter exists, else the CPU reference.
    Auto,
    Gpu,
    Cpu,
}

/// A validated `/v1/render` request.
#[derive(Debug, Clone, PartialEq)]
pub struct RenderParams {
    pub width: u32,
    pub height: u32,
    pub azimuth: f64,
    pub elevation: f64,
    /// `None`: 1.6 × the bounding-box diagonal.
    pub distance: Option<f64>,
    pub fov: f64,
    /// Explicit level, or one derived from `tol`, or the finest.
    pub level: Option<u8>,
    pub tol: Option<f64>,
    pub tf: String,
    pub renderer: RendererChoice,
}

impl RenderParams {
    /// Validates a query against a store with `levels` levels.
    pub fn parse(q: &HashMap<String, String>, levels: u8) -> Result<Self, String> {
        const KNOWN: [&str; 11] = [
            "width",
            "height",
            "azimuth",
            "elevation",
            "distance",
            "fov",
            "tol",
            "level",
            "tf",
            "renderer",
            "token",
        ];
        if let Some(k) = q.keys().find(|k| !KNOWN.contains(&k.as_str())) {
            return Err(format!("unknown parameter `{k}`"));
        }
        let num = |k: &str, default: f64| -> Result<f64, String> {
            match q.get(k) {
                None => Ok(default),
                Some(v) => {
                    let x: f64 = v
                        .trim()
                        .parse()
                        .map_err(|_| format!("`{k}` is not a number: {v:?}"))?;
                    if !x.is_finite() {
                        return Err(format!("`{k}` must be finite"));
                    }
                    Ok(x)
                }
            }
        };
        let side = |k: &str| -> Result<u32, String> {
            match q.get(k) {
                None => Ok(512),
                Some(v) => match v.trim().parse::<u64>() {
                    Ok(x) if (1..=MAX_SIDE as u64).contains(&x) => Ok(x as u32),
                    _ => Err(format!(
                        "`{k}` must be an integer in 1..={MAX_SIDE}, got {v:?}"
                    )),
                },
            }
        };
        let width = side("width")?;
        let height = side("height")?;
        let azimuth = num("azimuth", 35.0)?;
        if azimuth.abs() > 1e6 {
            return Err("`azimuth` out of range".into());
        }
        let elevation = num("elevation", 25.0)?;
        if !(-90.0..=90.0).contains(&elevation) {
            return Err(format!(
                "`elevation` must be within ±90 degrees, got {elevation}"
            ));
        }
        let distance = match q.get("distance") {
            None => None,
            Some(_) => {
                let d = num("distance", 0.0)?;
                if d <= 0.0 || d > 1e12 {
                    return Err(format!("`distance` must be > 0 (and sane), got {d}"));
                }
                Some(d)
            }
        };
        let fov = num("fov", 40.0)?;
        if !(1.0..=179.0).contains(&fov) {
            return Err(format!("`fov` must be within [1, 179] degrees, got {fov}"));
        }
        let tol = match q.get("tol") {
            None => None,
            Some(_) => {
                let t = num("tol", 0.0)?;
                if t < 0.0 {
                    return Err(format!("`tol` must be ≥ 0, got {t}"));
                }
                Some(t)
            }
        };
        let level = match q.get("level") {
            None => None,
            Some(v) => match v.trim().parse::<u8>() {
                Ok(l) if l <= levels => Some(l),
                _ => {
                    return Err(format!(
                        "`level` must be an integer in 0..={levels}, got {v:?}"
                    ))
                }
            },
        };
        if level.is_some() && tol.is_some() {
            return Err("give `level` or `tol`, not both".into());
        }
        let tf = q.get("tf").cloned().unwrap_or_else(|| "auto".into());
        if !TF_PRESETS.contains(&tf.as_str()) {
            return Err(format!(
                "unknown transfer function {tf:?} (presets: {})",
                TF_PRESETS.join(", ")
            ));
        }
        let renderer = match q.get("renderer").map(String::as_str) {
            None | Some("auto") => RendererChoice::Auto,
            Some("gpu") => RendererChoice::Gpu,
            Some("cpu") => RendererChoice::Cpu,
            Some(r) => return Err(format!("`renderer` must be auto, gpu or cpu, got {r:?}")),
        };
        Ok(RenderParams {
            width,
            height,
            azimuth,
            elevation,
            distance,
            fov,
            level,
            tol,
            tf,
            renderer,
        })
    }

    /// Eye distance: as asked, else the default framing's of `base`'s bounding box.
    pub fn eye_distance(&self, base: &BaseMesh) -> f64 {
        let (lo, hi) = base.bounds();
        self.distance
            .unwrap_or_else(|| Camera::framing(lo, hi).distance)
    }

    /// The uniform level to draw: `level`, or the coarsest whose tets' screen-space error
    /// `H/(2 tan(fov/2)) · diam/dist` is at most `tol` (at the volume's centre), or the finest.
    pub fn level_for(&self, base: &BaseMesh) -> u8 {
        if let Some(l) = self.level {
            return l;
        }
        let Some(tol) = self.tol.filter(|&t| t > 0.0) else {
            return base.levels;
        };
        let k = self.height as f64 / (2.0 * (0.5 * self.fov.to_radians()).tan());
        let dist = self.eye_distance(base);
        let diam0 = base_diameter(base);
        (0..=base.levels)
            .find(|&l| k * diam0 / (1u64 << l) as f64 / dist <= tol)
            .unwrap_or(base.levels)
    }
}

/// Longest edge over the base tets.
fn base_diameter(base: &BaseMesh) -> f64 {
    let mut d2 = 0.0f64;
    for t in &base.tets {
        for i in 0..4 {
            for j in i + 1..4 {
                let (p, q) = (base.positions[t[i] as usize], base.positions[t[j] as usize]);
                d2 = d2.max((0..3).map(|a| (p[a] - q[a]).powi(2)).sum());
            }
        }
    }
    d2.sqrt()
}

struct Gpu {
    ctx: GpuContext,
    renderer: PtRenderer,
    /// The last uploaded level.
    uploaded: Option<(u8, TetDrawData)>,
    /// The finest level whose mesh fits one buffer of this adapter, once a finer one did not:
    /// later requests draw at most this level without building the finer mesh again.
    max_level: Option<u8>,
}

struct RenderState {
    /// `None` until first asked; then the context or why there is none.
    gpu: Option<Result<Gpu, String>>,
    /// The last level's mesh.
    mesh: Option<(u8, Arc<RenderMesh>)>,
}

/// The store, its synthesized finest-level values and its nodes' empty-children masks.
/// An open store, its synthesized finest values, empty-children masks and level set.
type StoreData = (Store, Arc<Vec<f32>>, Vec<u8>, Option<Vec<f32>>);

/// Renders a store's uniform levels on request: synthesis once, meshes and GPU uploads of the last
/// level kept, one render at a time.
pub struct RenderService {
    /// Renders run on their own threads at a lower CPU priority (nice 10 on Linux), so a render never
    /// starves the stream and `/healthz` of CPU.
    pool: Option<rayon::ThreadPool>,
    dir: PathBuf,
    data: OnceLock<Result<StoreData, String>>,
    state: Mutex<RenderState>,
    counts: RenderCounts,
}

/// Renders started, finished, cancelled and running (for `/healthz` and tests).
#[derive(Default)]
struct RenderCounts {
    started: AtomicU64,
    finished: AtomicU64,
    cancelled: AtomicU64,
}

/// Decrements nothing; counts how a render ended when dropped.
struct Counting<'a> {
    counts: &'a RenderCounts,
    ended: bool,
}

impl Drop for Counting<'_> {
    fn drop(&mut self) {
        let c = if self.ended {
            &self.counts.finished
        } else {
            &self.counts.cancelled
        };
        c.fetch_add(1, Ordering::Relaxed);
    }
}

/// One rendered image and how.
pub struct Rendered {
    pub image: Rgba8Image,
    pub renderer: String,
    pub level: u8,
    pub tets: usize,
}

impl RenderService {
    pub fn new(dir: &Path) -> Self {
        let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .thread_name(|i| format!("render-{i}"))
            .start_handler(|_| lower_priority())
            .build()
            .map_err(|e| tracing::warn!("render threads: {e}; renders use the shared pool"))
            .ok();
        RenderService {
            pool,
            dir: dir.to_path_buf(),
            data: OnceLock::new(),
            state: Mutex::new(RenderState {
                gpu: None,
                mesh: None,
            }),
            counts: RenderCounts::default(),
        }
    }

    /// `{started, finished, cancelled, running}` so far, as JSON.
    pub fn counts(&self) -> serde_json::Value {
        let c = &self.counts;
        let (s, f, x) = (
            c.started.load(Ordering::Relaxed),
            c.finished.load(Ordering::Relaxed),
            c.cancelled.load(Ordering::Relaxed),
        );
        serde_json::json!({
            "started": s,
            "finished": f,
            "cancelled": x,
            "running": s.saturating_sub(f + x),
        })
    }

    fn data(&self) -> Result<&StoreData, String> {
        self.data
            .get_or_init(|| {
                let s = Store::open(&self.dir).map_err(|e| e.to_string())?;
                let v = s.synthesize_all().map_err(|e| e.to_string())?;
                let empty = s.empty_children().map_err(|e| e.to_string())?;
                let levelset = s.read_levelset().map_err(|e| e.to_string())?;
                Ok((s, Arc::new(v), empty, levelset))
            })
            .as_ref()
            .map_err(|e| e.clone())
    }

    /// Renders one image (blocking: call from a blocking thread). `Err((status, message))`. When
    /// `cancel` becomes true the CPU integrator stops within a row and this returns 503; a GPU
    /// render is checked before it starts.
    pub fn render(
        &self,
        p: &RenderParams,
        cancel: &AtomicBool,
    ) -> Result<Rendered, (StatusCode, String)> {
        self.counts.started.fetch_add(1, Ordering::Relaxed);
        let mut counting = Counting {
            counts: &self.counts,
            ended: false,
        };
        let r = self.render_counted(p, cancel);
        counting.ended = r.is_ok() || !cancel.load(Ordering::Relaxed);
        r
    }

    fn render_counted(
        &self,
        p: &RenderParams,
        cancel: &AtomicBool,
    ) -> Result<Rendered, (StatusCode, String)> {
        let internal = |e: String| (StatusCode::INTERNAL_SERVER_ERROR, e);
        let cancelled = || {
            (
                StatusCode::SERVICE_UNAVAILABLE,
                "the render was cancelled".to_string(),
            )
        };
        let (store, values, empty, levelset) = self.data().map_err(internal)?;
        let base = &store.base;
        let level = p.level_for(base);
        let tf = TransferFunction::for_manifest(&p.tf, &store.manifest)
            .map_err(|e| (StatusCode::BAD_REQUEST, e.to_string()))?;
        let mut st = self.state.lock().unwrap_or_else(|e| e.into_inner());
        if cancel.load(Ordering::Relaxed) {
            return Err(cancelled());
        }
        let mesh_at = |st: &mut RenderState, level: u8| match &st.mesh {
            Some((l, m)) if *l == level => m.clone(),
            _ => {
                // the mesh of another level is dropped before this one is built
                st.mesh = None;
                let mut m = RenderMesh::uniform_level_clipped(
                    base,
                    values,
                    empty,
                    level,
                    levelset.as_deref(),
                );
                let [lo, hi] = store.manifest.display_value_range();
                m.value_range = (lo, hi);
                let m = Arc::new(m);
                st.mesh = Some((level, m.clone()));
                m
            }
        };
        let mut level = level;
        if let (
            true,
            Some(Ok(Gpu {
                max_level: Some(max),
                ..
            })),
        ) = (p.renderer != RendererChoice::Cpu, &st.gpu)
        {
            level = level.min(*max);
        }
        let mut mesh = mesh_at(&mut st, level);
        let cam = Orbit {
            target: mesh.center(),
            distance: p.eye_distance(base),
            azimuth: p.azimuth,
            elevation: p.elevation,
            fov: p.fov,
        }
        .camera(p.width, p.height);
        let want_gpu = p.renderer != RendererChoice::Cpu;
        if want_gpu && st.gpu.is_none() {
            st.gpu = Some(
                GpuContext::new()
                    .map(|ctx| Gpu {
                        renderer: PtRenderer::new(&ctx),
                        ctx,
                        uploaded: None,
                        max_level: None,
                    })
                    .map_err(|e| e.to_string()),
            );
        }
        if want_gpu {
            match st.gpu.as_mut().expect("set above") {
                Ok(g) => {
                    if g.uploaded.as_ref().is_none_or(|(l, _)| *l != level) {
                        g.uploaded = None;
                        let d = match g.renderer.upload(&g.ctx, &mesh) {
                            Ok(d) => d,
                            // more tets than one buffer of this adapter holds: the finest
                            // coarser level that fits (each level has 8x the tets of the last)
                            Err(RenderError::TooLarge { needed, limit }) if level > 0 => {
                                let fits = finest_fitting_level(
                                    base.tets.len(),
                                    level,
                                    needed as f64 / mesh.tets.len().max(1) as f64,
                                    limit,
                                );
                                let Some(l) = fits else {
                                    return Err(internal(format!(
                                        "no level of this store fits one GPU buffer of {limit} bytes"
                                    )));
                                };
                                tracing::info!(
                                    asked = level,
                                    drawn = l,
                                    "level {level} needs {needed} bytes in one GPU buffer \
                                     (this adapter allows {limit}): drawing level {l}"
                                );
                                level = l;
                                mesh = mesh_at(&mut st, level);
                                let g = st.gpu.as_mut().expect("set above").as_mut().expect("ok");
                                g.max_level = Some(l);
                                g.renderer
                                    .upload(&g.ctx, &mesh)
                                    .map_err(|e| internal(e.to_string()))?
                            }
                            Err(e) => return Err(internal(e.to_string())),
                        };
                        let g = st.gpu.as_mut().expect("set above").as_mut().expect("ok");
                        g.uploaded = Some((level, d));
                    }
                    let g = st.gpu.as_mut().expect("set above").as_mut().expect("ok");
                    let data = &g.uploaded.as_ref().expect("uploaded").1;
                    let (image, _) = g
                        .renderer
                        .render(&g.ctx, data, &cam, &tf)
                        .map_err(|e| internal(e.to_string()))?;
                    return Ok(Rendered {
                        image,
                        renderer: format!("gpu-pt {}", g.ctx.describe()),
                        level,
                        tets: mesh.tets.len(),
                    });
                }
                Err(e) if p.renderer == RendererChoice::Gpu => {
                    return Err((StatusCode::SERVICE_UNAVAILABLE, format!("no GPU: {e}")));
                }
                Err(_) => {}
            }
        }
        // only the lock-free integrator runs on the render pool: a pool thread waiting inside it may
        // run another queued pool job, which must never be one that takes `state`
        let trace = || render_reference_cancellable(&mesh, &cam, &tf, cancel);
        let image = match &self.pool {
            Some(pool) => pool.install(trace),
            None => trace(),
        }
        .ok_or_else(cancelled)?;
        Ok(Rendered {
            image,
            renderer: "cpu-reference".into(),
            level,
            tets: mesh.tets.len(),
        })
    }
}

/// The finest level below `level` whose uniform mesh (`base_tets` × 8^l tets at `per_tet` bytes
/// each) fits one GPU buffer of `limit` bytes, if any.
fn finest_fitting_level(base_tets: usize, level: u8, per_tet: f64, limit: u64) -> Option<u8> {
    (0..level)
        .rev()
        .find(|&l| base_tets as f64 * 8f64.powi(l as i32) * per_tet <= limit as f64)
}

/// Lowers the calling thread's CPU priority to nice 10 (Linux: `setpriority` on a thread id applies
/// to that thread only); elsewhere nothing.
fn lower_priority() {
    #[cfg(target_os = "linux")]
    // SAFETY: plain system calls on the calling thread's own id; failure only leaves the priority
    unsafe {
        let tid = libc::syscall(libc::SYS_gettid) as libc::id_t;
        libc::setpriority(libc::PRIO_PROCESS, tid, 10);
    }
}

/// The fallback viewer page (`GET /`) for the store of manifest `m`: one self-contained HTML
/// document, with a colour legend (the dataset's name, the value range the transfer functions
/// span, and the chosen one's colours across it; `auto`, fitted to the store's histogram, first).
pub fn page_html(m: &Manifest) -> String {
    use tetwave_render::legend::{css_gradient, legend_text};
    let (dataset, range) = (m.dataset.as_str(), m.display_value_range());
    let gradients: Vec<String> = TF_PRESETS
        .iter()
        .filter_map(|name| {
            let tf = TransferFunction::for_manifest(name, m).ok()?;
            Some(format!("{name:?}: {:?}", css_gradient(&tf, 17)))
        })
        .collect();
    PAGE.replace("{{DATASET}}", &html_escape(dataset))
        .replace(
            "{{LEGEND}}",
            &html_escape(&legend_text(&m.legend_name(), range)),
        )
        .replace("{{GRADIENTS}}", &gradients.join(", "))
}

fn html_escape(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
}

const PAGE: &str = r#"<!doctype html>
<html lang="en"><head><meta charset="utf-8">
<title>tetwave: {{DATASET}}</title>
<style>
 body { background:#111; color:#ddd; font:14px sans-serif; margin:1em; }
 #view { background:#000; cursor:grab; user-select:none; display:block; width:512px; height:512px; }
 #view.drag { cursor:grabbing; }
 label { margin-right:1em; }
 #legend { width:512px; margin-top:6px; font-family:monospace; }
 #lbar { height:12px; margin-bottom:2px; }
</style></head>
<body>
<h3>tetwave &mdash; {{DATASET}} (server-rendered fallback)</h3>
<img id="view" width="512" height="512" alt="rendering" draggable="false">
<div id="legend"><div id="lbar"></div><span id="ltext">{{LEGEND}}</span></div>
<p>
 <label>tolerance <input id="tol" type="range" min="0" max="64" step="0.5" value="2"> <span id="tolv">2</span> px</label>
 <label>transfer function <select id="tf"><option>auto</option><option>default</option><option>transparent</option><option>opaque</option><option>shells</option></select></label>
</p>
<p id="info">drag to orbit</p>
<script>
(function () {
  const img = document.getElementById('view'), tol = document.getElementById('tol');
  const tolv = document.getElementById('tolv'), tf = document.getElementById('tf');
  const info = document.getElementById('info');
  const GRADIENTS = { {{GRADIENTS}} };
  function legend() { document.getElementById('lbar').style.background = GRADIENTS[tf.value] || ''; }
  const token = new URLSearchParams(location.search).get('token');
  let az = 35, el = 25, busy = false, again = false, drag = null;
  function url() {
    const q = new URLSearchParams({width: 512, height: 512, azimuth: az.toFixed(2),
      elevation: el.toFixed(2), tol: tol.value, tf: tf.value});
    if (token) q.set('token', token);
    return '/v1/render?' + q.toString();
  }
  function refresh() {
    if (busy) { again = true; return; }
    busy = true;
    const t0 = performance.now();
    fetch(url()).then(r => {
      if (!r.ok) return r.text().then(t => { throw new Error(r.status + ' ' + t); });
      const lvl = r.headers.get('x-tetwave-level'), who = r.headers.get('x-tetwave-renderer');
      return r.blob().then(b => {
        const old = img.src; img.src = URL.createObjectURL(b);
        if (old.startsWith('blob:')) URL.revokeObjectURL(old);
        info.textContent = 'level ' + lvl + ', ' + who + ', ' + Math.round(performance.now() - t0) +
          ' ms; azimuth ' + az.toFixed(1) + ', elevation ' + el.toFixed(1);
      });
    }).catch(e => { info.textContent = 'error: ' + e.message; })
      .finally(() => { busy = false; if (again) { again = false; refresh(); } });
  }
  img.addEventListener('mousedown', e => { drag = [e.clientX, e.clientY]; img.classList.add('drag'); e.preventDefault(); });
  window.addEventListener('mouseup', () => { if (drag) { drag = null; img.classList.remove('drag'); refresh(); } });
  window.addEventListener('mousemove', e => {
    if (!drag) return;
    az -= (e.clientX - drag[0]) * 0.5;
    el = Math.max(-89, Math.min(89, el + (e.clientY - drag[1]) * 0.5));
    drag = [e.clientX, e.clientY];
    refresh();
  });
  tol.addEventListener('input', () => { tolv.textContent = tol.value; refresh(); });
  tf.addEventListener('change', () => { legend(); refresh(); });
  legend();
  refresh();
})();
</script>
</body></html>
"#;

#[cfg(test)]
mod tests {
    use super::finest_fitting_level;

    /// A 129³ box6 store's level 7 (12.6 M tets at 96 bytes) in lavapipe's 128 MiB buffer: level
    /// 5 (196,608 tets) fits and level 6 (1.57 M) does not; nothing fits a buffer too small for
    /// the base mesh.
    #[test]
    fn the_finest_level_that_fits_one_buffer() {
        let limit = 128 << 20;
        assert_eq!(finest_fitting_level(6, 7, 96.0, limit), Some(5));
        assert_eq!(finest_fitting_level(6, 6, 96.0, limit), Some(5));
        assert_eq!(finest_fitting_level(6, 5, 96.0, 6 * 8 * 8 * 96), Some(2));
        assert_eq!(finest_fitting_level(6, 3, 96.0, 100), None);
        assert_eq!(finest_fitting_level(6, 0, 96.0, limit), None);
    }
}
