// Projected tetrahedra with exit-point integration (tetwave, client/src/render/pt.rs).
//
// Tets are drawn back to front; only each tet's exit faces (outward normal pointing away from the
// eye) are rasterized. The fragment on an exit face knows where the pixel's ray leaves the tet; it finds where the ray
// entered from the tet's face planes (clamped to the near plane, so a camera inside the mesh works),
// evaluates the normalized scalar at both ends from the tet's linear gradient, and integrates
// emission–absorption along the chord with the transfer function (midpoint sub-steps). Output is
// premultiplied; blending is `over` (src ONE, dst ONE_MINUS_SRC_ALPHA).
//
// Spaces: every position is world space relative to `origin` (chosen by the CPU near the mesh's
// centre, so large coordinate offsets do not cost f32 precision).

struct Globals {
    view_proj: mat4x4<f32>,
    // xyz: eye position; w: near-plane distance along the view direction
    eye: vec4<f32>,
    // xyz: unit view direction; w: extinction scale (1 / bounding-box diagonal)
    fwd: vec4<f32>,
    // x: number of transfer-function points; y: scalar resolution for sub-steps (as f32 bits);
    // z: max extinction (per diagonal, f32 bits)
    tf_info: vec4<u32>,
};

// Per tet: 4 outward face planes (xyz normal, w offset: n·x = w on the face) and the linear
// normalized scalar s(x) = grad.xyz · x + grad.w.
struct TetGeo {
    planes: array<vec4<f32>, 4>,
    grad: vec4<f32>,
};

// Transfer-function point: a = (s, r, g, b), b = (extinction per diagonal, 0, 0, 0).
struct TfPoint {
    a: vec4<f32>,
    b: vec4<f32>,
};

@group(0) @binding(0) var<uniform> globals: Globals;
@group(0) @binding(1) var<storage, read> positions: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> tets: array<vec4<u32>>;
@group(0) @binding(3) var<storage, read> geo: array<TetGeo>;
@group(0) @binding(5) var<storage, read> tf: array<TfPoint>;

struct VsOut {
    @builtin(position) clip: vec4<f32>,
    // world position (relative to origin) on the exit face
    @location(0) world: vec3<f32>,
    @location(1) @interpolate(flat) tet: u32,
};

// Indexed draw: vertex `v` is corner `v % 4` of tet `v / 4`; the CPU's index buffer lists each tet's
// 4 faces (outward winding counter-clockwise) in back-to-front tet order, and the rasterizer culls
// front faces, so only exit faces reach the fragment stage. Each tet's 4 corners are shaded once and
// reused by its 4 faces.
@vertex
fn vs_main(@builtin(vertex_index) vi: u32) -> VsOut {
    let t = vi / 4u;
    let p = positions[tets[t][vi % 4u]].xyz;
    var out: VsOut;
    out.world = p;
    out.tet = t;
    out.clip = globals.view_proj * vec4<f32>(p, 1.0);
    return out;
}

fn tf_eval(s: f32) -> vec4<f32> {
    // returns (r, g, b, extinction per diagonal), piecewise linear, clamped at the ends
    let n = globals.tf_info.x;
    let first = tf[0u];
    if (s <= first.a.x || n == 1u) {
        return vec4<f32>(first.a.yzw, first.b.x);
    }
    for (var i = 1u; i < n; i = i + 1u) {
        let q = tf[i];
        if (s <= q.a.x) {
            let p = tf[i - 1u];
            let span = q.a.x - p.a.x;
            var u = 1.0;
            if (span > 0.0) { u = (s - p.a.x) / span; }
            return mix(vec4<f32>(p.a.yzw, p.b.x), vec4<f32>(q.a.yzw, q.b.x), u);
        }
    }
    let last = tf[n - 1u];
    return vec4<f32>(last.a.yzw, last.b.x);
}

@fragment
fn fs_main(in: VsOut) -> @location(0) vec4<f32> {
    let g = geo[in.tet];
    // zero-volume tets have zero planes: they contribute nothing
    if (dot(g.planes[0].xyz, g.planes[0].xyz) == 0.0) {
        discard;
    }
    let eye = globals.eye.xyz;
    var dir = in.world - eye;
    let t_exit = length(dir);
    if (!(t_exit > 0.0)) {
        discard;
    }
    dir = dir / t_exit;
    // rays start at the near plane
    var t_in = globals.eye.w / max(dot(dir, globals.fwd.xyz), 1e-6);
    for (var i = 0u; i < 4u; i = i + 1u) {
        let pl = g.planes[i];
        let den = dot(pl.xyz, dir);
        if (den < 0.0) {
            t_in = max(t_in, (pl.w - dot(pl.xyz, eye)) / den);
        }
    }
    let len = t_exit - t_in;
    if (!(len > 0.0) || len > 1e30) {
        discard;
    }
    let s0 = dot(g.grad.xyz, eye + dir * t_in) + g.grad.w;
    let s1 = dot(g.grad.xyz, in.world) + g.grad.w;
    let ext_scale = globals.fwd.w;
    let s_res = bitcast<f32>(globals.tf_info.y);
    // sub-steps: each step uses the exact absorption of its own constant extinction, so the error
    // comes only from the transfer function varying within a step: bound the scalar change per step
    let steps = u32(clamp(ceil(abs(s1 - s0) / s_res), 1.0, 64.0));
    let h = len / f32(steps);
    var col = vec3<f32>(0.0);
    var tr = 1.0;
    for (var i = 0u; i < steps; i = i + 1u) {
        let u = (f32(i) + 0.5) / f32(steps);
        let e = tf_eval(mix(s0, s1, u));
        let a = 1.0 - exp(-e.w * ext_scale * h);
        col = col + tr * e.xyz * a;
        tr = tr * (1.0 - a);
    }
    return vec4<f32>(col, 1.0 - tr);
}
