// Projected tetrahedra with exit-point integration (tetwave, client/src/render/pt.rs).
//
// Tets are drawn back to front; only each tet's exit faces (outward normal pointing away from the
// eye) are rasterized. The fragment on an exit face knows where the pixel's ray leaves the tet; it finds where the ray
// entered from the tet's face planes (clamped to the near plane, so a camera inside the mesh works),
// takes the normalized scalar at both ends (linear in the tet), and integrates emission–absorption
// along the chord with the transfer function (midpoint sub-steps). Output is premultiplied; blending
// is `over` (src ONE, dst ONE_MINUS_SRC_ALPHA).
//
// Domain clipping: each tet also carries the domain's level set φ (linear in the tet; ≡ 1 when the
// mesh has none). The chord is cut to the part where φ ≥ 0 (φ is linear along the ray, so the cut
// is one division) and the scalar re-interpolated at the cut ends: a tet that straddles the
// domain's boundary draws only what lies inside.
//
// Two fragment entry points (two pipelines; the CPU draws each tet with one of them):
// - `fs_main`: exactly two sub-steps, straight-line code, for tets whose scalar range is at most four
//   sub-step resolutions (`FAST_MAX_STEPS` in pt.rs; all tets of a fine mesh). A loop in a lavapipe
//   fragment shader is expensive even when few pixels run it, so this has none.
// - `fs_steps`: as many sub-steps as the scalar change needs (2 to 64), for tets with a larger range.
//
// Spaces: every position is world space relative to `origin` (chosen by the CPU near the mesh's
// centre, so large coordinate offsets do not cost f32 precision).

struct Globals {
    view_proj: mat4x4<f32>,
    // xyz: eye position; w: near-plane distance along the view direction
    eye: vec4<f32>,
    // xyz: unit view direction; w: extinction scale (1 / bounding-box diagonal)
    fwd: vec4<f32>,
    // x: number of transfer-function table intervals; y: scalar resolution for sub-steps (f32 bits);
    // z: max extinction (per diagonal, f32 bits)
    tf_info: vec4<u32>,
};

// Per tet: 4 outward face planes (xyz normal, w offset: n·x = w on the face), the linear
// normalized scalar s(x) = grad.xyz · x + grad.w and the linear level set φ(x) = lset.xyz · x +
// lset.w (drawn where φ ≥ 0).
struct TetGeo {
    planes: array<vec4<f32>, 4>,
    grad: vec4<f32>,
    lset: vec4<f32>,
};

// The transfer function tabulated at `tf_info.x + 1` evenly spaced normalized scalars: (r, g, b,
// extinction per diagonal); linear interpolation between entries.
@group(0) @binding(0) var<uniform> globals: Globals;
@group(0) @binding(1) var<storage, read> positions: array<vec4<f32>>;
@group(0) @binding(2) var<storage, read> tets: array<vec4<u32>>;
@group(0) @binding(3) var<storage, read> geo: array<TetGeo>;
// (A uniform array: lavapipe reads storage buffers at per-pixel indices one lane at a time.) 4096 entries fill the 64 KiB that every adapter allows for a uniform binding.
@group(0) @binding(5) var<uniform> tf: array<vec4<f32>, 4096>;

struct VsOut {
    @builtin(position) clip: vec4<f32>,
    // xyz: ray vector d from the eye to this point of the exit face (the ray is eye + λ·d, λ = 1 at
    // the exit); w: the normalized scalar here (linear over the face)
    @location(0) d: vec4<f32>,
    // n_i·d for the tet's 4 outward face normals (linear over the face, so interpolated instead of
    // computed per fragment)
    @location(1) den: vec4<f32>,
    // per tet, constant over it: c_i = w_i - n_i·eye (the ray meets plane i at λ = c_i / (n_i·d))
    @location(2) @interpolate(flat) c: vec4<f32>,
    // the tet's linear scalar (x) and level set (y) extended to the eye
    @location(3) @interpolate(flat) eye_vals: vec2<f32>,
    // the level set here (linear over the face)
    @location(4) phi: f32,
};

// Indexed draw: vertex `v` is corner `v % 4` of tet `v / 4`; the CPU's index buffer lists, in
// back-to-front tet order, only each tet's exit faces (outward winding counter-clockwise), and the
// rasterizer also culls front faces, so only exit faces reach the fragment stage.
@vertex
fn vs_main(@builtin(vertex_index) vi: u32) -> VsOut {
    return tet_vertex(vi / 4u, vi % 4u);
}

// The GPU's visibility order (gpu/src/sort.rs): the chunk's tets back to front, and a bit per tet
// set when it is negatively oriented (its faces wind the other way).
@group(1) @binding(0) var<storage, read> order: array<u32>;
@group(1) @binding(1) var<storage, read> negative: array<u32>;

// Non-indexed draw in the GPU's order: vertex `v` is corner `k` of face `(v % 12) / 3` of the tet
// at `order[v / 12]`, every face of every tet drawn; front-face culling drops the entry faces, as
// the CPU drops them before drawing (`FACES_POS`/`FACES_NEG` in pt.rs).
@vertex
fn vs_sorted(@builtin(vertex_index) vi: u32) -> VsOut {
    let t = order[vi / 12u];
    var pos = array<u32, 12>(1u, 2u, 3u, 0u, 3u, 2u, 0u, 1u, 3u, 0u, 2u, 1u);
    var neg = array<u32, 12>(1u, 3u, 2u, 0u, 2u, 3u, 0u, 3u, 1u, 0u, 1u, 2u);
    let k = vi % 12u;
    let flip = ((negative[t >> 5u] >> (t & 31u)) & 1u) == 1u;
    return tet_vertex(t, select(pos[k], neg[k], flip));
}

// Corner `corner` of tet `t`, with what the fragment stage needs of the tet.
fn tet_vertex(t: u32, corner: u32) -> VsOut {
    let p = positions[tets[t][corner]].xyz;
    let eye = globals.eye.xyz;
    let g = geo[t];
    let pl = g.planes;
    let nx = vec4<f32>(pl[0].x, pl[1].x, pl[2].x, pl[3].x);
    let ny = vec4<f32>(pl[0].y, pl[1].y, pl[2].y, pl[3].y);
    let nz = vec4<f32>(pl[0].z, pl[1].z, pl[2].z, pl[3].z);
    let d = p - eye;
    var out: VsOut;
    out.d = vec4<f32>(d, dot(g.grad.xyz, p) + g.grad.w);
    out.den = nx * d.x + ny * d.y + nz * d.z;
    out.c = vec4<f32>(pl[0].w, pl[1].w, pl[2].w, pl[3].w) - (nx * eye.x + ny * eye.y + nz * eye.z);
    out.eye_vals = vec2<f32>(dot(g.grad.xyz, eye) + g.grad.w, dot(g.lset.xyz, eye) + g.lset.w);
    out.phi = dot(g.lset.xyz, p) + g.lset.w;
    out.clip = globals.view_proj * vec4<f32>(p, 1.0);
    return out;
}

fn tf_eval(s: f32) -> vec4<f32> {
    // returns (r, g, b, extinction per diagonal), clamped at the ends; interpolated, not the nearest
    // entry, which is visibly wrong where the scalar sits between entries on a steep part of the
    // function (e.g. a constant field)
    let n = globals.tf_info.x;
    let x = clamp(s, 0.0, 1.0) * f32(n);
    let k = min(u32(x), n - 1u);
    return mix(tf[k], tf[k + 1u], x - f32(k));
}

// The ray's chord through the tet, clipped to the domain (φ ≥ 0): (entry scalar, exit scalar,
// world length); length ≤ 0 or NaN: none.
fn chord(in: VsOut) -> vec3<f32> {
    let d = in.d.xyz;
    // rays start at the near plane; the entry is the farthest crossing of a plane the ray enters by
    let hits = select(vec4<f32>(-1e30), in.c / in.den, in.den < vec4<f32>(0.0));
    let l_near = globals.eye.w / max(dot(d, globals.fwd.xyz), 1e-30);
    var a = max(l_near, max(max(hits.x, hits.y), max(hits.z, hits.w)));
    var b = 1.0;
    // φ is linear in the ray parameter λ: φ(λ) = mix(φ_eye, φ_exit, λ); keep the part ≥ 0
    let pa = mix(in.eye_vals.y, in.phi, a);
    let pb = in.phi;
    if (pa < 0.0 && pb < 0.0) {
        return vec3<f32>(0.0, 0.0, -1.0);
    }
    if (pa < 0.0 || pb < 0.0) {
        let cut = a + (b - a) * clamp(pa / (pa - pb), 0.0, 1.0);
        if (pa < 0.0) {
            a = cut;
        } else {
            b = cut;
        }
    }
    let len = (b - a) * sqrt(dot(d, d));
    return vec3<f32>(mix(in.eye_vals.x, in.d.w, a), mix(in.eye_vals.x, in.d.w, b), len);
}

@fragment
fn fs_main(in: VsOut) -> @location(0) vec4<f32> {
    let ch = chord(in);
    let len = ch.z;
    if (!(len > 0.0) || len > 1e30) {
        discard;
    }
    // two midpoint sub-steps (each with the exact absorption of its own constant extinction), the
    // front one composited over the back one
    let h = 0.5 * len * globals.fwd.w;
    let ef = tf_eval(mix(ch.x, ch.y, 0.25));
    let eb = tf_eval(mix(ch.x, ch.y, 0.75));
    let af = 1.0 - exp(-ef.w * h);
    let ab = 1.0 - exp(-eb.w * h);
    return vec4<f32>(ef.xyz * af + (1.0 - af) * eb.xyz * ab, 1.0 - (1.0 - af) * (1.0 - ab));
}

@fragment
fn fs_steps(in: VsOut) -> @location(0) vec4<f32> {
    let ch = chord(in);
    let len = ch.z;
    if (!(len > 0.0) || len > 1e30) {
        discard;
    }
    let s0 = ch.x;
    let s1 = ch.y;
    let ext_scale = globals.fwd.w;
    let s_res = bitcast<f32>(globals.tf_info.y);
    // sub-steps: each step uses the exact absorption of its own constant extinction, so the error
    // comes only from the transfer function varying within a step: bound the scalar change per step
    let steps = u32(clamp(ceil(abs(s1 - s0) / s_res), 2.0, 64.0));
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
