// surfel-gpu: the surfel map on the device. Every kernel mirrors a function of
// plugins/src/fuse/surfel_rules.rs or surfel_cpu/ line for line (same f32 operations in the
// same order). The index map's z-test is resolved in two passes (atomic minimum of the depth
// bits, then of the index among the surfels at that depth), which equals the CPU's atomic
// minimum of (depth bits << 32 | index); the prediction's ε-z-buffer in three (nearest depth,
// most confident within ε with the confidence capped at P.stable, lowest index), which equals
// the CPU's atomic maximum of (capped confidence key << 32 | !index): the map and its
// predictions are deterministic.

struct Surfel {
    pos: vec3<f32>,
    conf: f32,
    nrm: vec3<f32>,
    radius: f32,
    colour: u32,
    t0: u32,
    t: u32,
    albedo: f32,
    sigma: f32,
    // The displacement the trackers' warps gave it (host-side; the kernels only carry it).
    warp_x: f32,
    warp_y: f32,
    warp_z: f32,
}

struct Measurement {
    pos: vec3<f32>,
    conf: f32,
    nrm: vec3<f32>,
    radius: f32,
    colour: u32,
    albedo: f32,
    pixel: u32,
    z_live: f32,
    n_cam: vec3<f32>,
    lambda: f32,
    ray: vec3<f32>,
    sigma: f32,
}

struct ViewPixel {
    depth: f32,
    nx: f32,
    ny: f32,
    nz: f32,
    colour: u32,
    conf: f32,
    t0: u32,
    t: u32,
    albedo: f32,
    sigma: f32,
}

struct Params {
    t_cw: mat4x4<f32>,
    fx: f32, fy: f32, cx: f32, cy: f32,
    width: u32, height: u32, n_surfels: u32, n_meas: u32,
    now: u32, delta_t: u32, life: u32, model_set: u32,
    stable: f32, min_depth: f32, max_depth: f32, depth_gate: f32,
    normal_gate: f32, bypass_nz: f32, radius_ratio: f32, scan_base: u32,
    scan_n: u32, scan_slot: u32, add_base: u32, blend: f32,
    revisit: u32, revisit_gate: f32, revisit_after: u32, pad1: u32,
}

const EMPTY: u32 = 0xffffffffu;

@group(0) @binding(0) var<uniform> P: Params;
@group(0) @binding(1) var<storage, read_write> surf_a: array<Surfel>;
@group(0) @binding(2) var<storage, read_write> surf_b: array<Surfel>;
@group(0) @binding(3) var<storage, read> meas: array<Measurement>;
@group(0) @binding(4) var<storage, read_write> zdepth: array<atomic<u32>>;
@group(0) @binding(5) var<storage, read_write> zid: array<atomic<u32>>;
@group(0) @binding(6) var<storage, read_write> winner: array<atomic<u32>>;
@group(0) @binding(7) var<storage, read_write> flags: array<u32>;
@group(0) @binding(8) var<storage, read_write> offsets: array<u32>;
@group(0) @binding(9) var<storage, read_write> blocks: array<u32>;
@group(0) @binding(10) var<storage, read_write> counters: array<atomic<u32>>;
@group(0) @binding(11) var<storage, read_write> view: array<ViewPixel>;
@group(0) @binding(12) var<storage, read_write> zconf: array<atomic<u32>>;

var<workgroup> sh: array<u32, 256>;

fn since(now: u32, t: u32) -> u32 {
    return select(0u, now - t, now > t);
}

fn is_active(s: Surfel) -> bool {
    return since(P.now, s.t) <= P.delta_t;
}

fn to_cam(p: vec3<f32>) -> vec3<f32> {
    return (P.t_cw * vec4<f32>(p, 1.0)).xyz;
}

fn rot_cam(n: vec3<f32>) -> vec3<f32> {
    return (P.t_cw * vec4<f32>(n, 0.0)).xyz;
}

// Rust's f32::round (half away from zero; WGSL's round is half to even).
fn round_away(x: f32) -> f32 {
    return select(-floor(-x + 0.5), floor(x + 0.5), x >= 0.0);
}

// The same for the non-negative values where only those occur.
fn round_pos(x: f32) -> f32 {
    return floor(x + 0.5);
}

@compute @workgroup_size(256)
fn clear_z(@builtin(global_invocation_id) g: vec3<u32>) {
    let k = g.x;
    if (k >= P.width * P.height) { return; }
    atomicStore(&zdepth[k], EMPTY);
    atomicStore(&zid[k], EMPTY);
    atomicStore(&zconf[k], 0u);
}

// The index map (surfel_cpu::IndexMap::render): active surfels as 1-pixel points and, with
// P.revisit, stable inactive ones last seen since the map's last warp behind them
// (surfel_rules::revisit_layer, window::ActiveWindow::revisits).
fn index_pixel(i: u32) -> i32 {
    let s = surf_a[i];
    if (!is_active(s) && !(P.revisit != 0u && s.conf >= P.stable && s.t >= P.revisit_after)) { return -1; }
    let p = to_cam(s.pos);
    if (p.z <= 0.0 || p.z > P.max_depth) { return -1; }
    let u = round_pos(P.fx * p.x / p.z + P.cx);
    let v = round_pos(P.fy * p.y / p.z + P.cy);
    if (u < 0.0 || v < 0.0 || u >= f32(P.width) || v >= f32(P.height)) { return -1; }
    return i32(u32(v) * P.width + u32(u));
}

// The z-test key of the index map: a positive depth's bits stay below 2^31, so the top bit
// puts an inactive surfel behind every active one (the CPU's bit 63).
fn index_key(i: u32) -> u32 {
    let s = surf_a[i];
    return bitcast<u32>(to_cam(s.pos).z) | select(0x80000000u, 0u, is_active(s));
}

@compute @workgroup_size(256)
fn index_depth(@builtin(global_invocation_id) g: vec3<u32>) {
    let i = g.x;
    if (i >= P.n_surfels) { return; }
    let k = index_pixel(i);
    if (k < 0) { return; }
    atomicMin(&zdepth[u32(k)], index_key(i));
}

@compute @workgroup_size(256)
fn index_id(@builtin(global_invocation_id) g: vec3<u32>) {
    let i = g.x;
    if (i >= P.n_surfels) { return; }
    let k = index_pixel(i);
    if (k < 0) { return; }
    if (atomicLoad(&zdepth[u32(k)]) == index_key(i)) {
        atomicMin(&zid[u32(k)], i);
    }
}

// surfel_rules::depth_gate (`gate`: depth_gate_m, or revisit_gate_m for an inactive surfel)
// and normal_gate.
fn gates(pm: vec3<f32>, nm: vec3<f32>, m: Measurement, gate: f32) -> bool {
    if (!(abs(pm.z - m.z_live) * m.lambda < gate)) { return false; }
    return abs(nm.z) < P.bypass_nz || acos(clamp(dot(nm, m.n_cam), -1.0, 1.0)) < P.normal_gate;
}

// Association (SurfelCpu::associate): the candidate of the 3×3 neighbourhood nearest the
// pixel ray wins, an active one before any inactive one (first in row order on a tie); the last measurement in pixel order that
// picks a surfel updates it (atomic maximum of its index + 1); the others are added.
@compute @workgroup_size(256)
fn associate(@builtin(global_invocation_id) g: vec3<u32>) {
    let j = g.x;
    if (j >= P.n_meas) { return; }
    let m = meas[j];
    let x = m.pixel % P.width;
    let y = m.pixel / P.width;
    var best = EMPTY;
    var best_d = 0.0;
    var best_behind = false;
    let y0 = select(0u, y - 1u, y > 0u);
    let x0 = select(0u, x - 1u, x > 0u);
    let y1 = min(y + 1u, P.height - 1u);
    let x1 = min(x + 1u, P.width - 1u);
    for (var yy = y0; yy <= y1; yy = yy + 1u) {
        for (var xx = x0; xx <= x1; xx = xx + 1u) {
            let k = yy * P.width + xx;
            let i = atomicLoad(&zid[k]);
            if (i == EMPTY) { continue; }
            let pm = to_cam(surf_a[i].pos);
            let nm = rot_cam(surf_a[i].nrm);
            let behind = !is_active(surf_a[i]);
            if (!gates(pm, nm, m, select(P.depth_gate, P.revisit_gate, behind))) { continue; }
            let perp = length(pm - m.ray * dot(pm, m.ray));
            if (best == EMPTY || (!behind && best_behind) || (behind == best_behind && perp < best_d)) {
                best = i;
                best_d = perp;
                best_behind = behind;
            }
        }
    }
    if (best == EMPTY) {
        flags[P.add_base + j] = 1u;
    } else {
        flags[P.add_base + j] = 0u;
        atomicMax(&winner[best], j + 1u);
    }
}

fn unpack_colour(c: u32) -> vec3<f32> {
    return vec3<f32>(f32(c & 0xffu), f32((c >> 8u) & 0xffu), f32((c >> 16u) & 0xffu));
}

// surfel_rules::merge.
@compute @workgroup_size(256)
fn merge(@builtin(global_invocation_id) g: vec3<u32>) {
    let i = g.x;
    if (i >= P.n_surfels) { return; }
    let w = atomicLoad(&winner[i]);
    if (w == 0u) { return; }
    let m = meas[w - 1u];
    var s = surf_a[i];
    let c = s.conf;
    let a = m.conf;
    if (m.radius < P.radius_ratio * s.radius) {
        let k = 1.0 / (c + a);
        let q = select(1.0, s.sigma / m.sigma, s.sigma > 0.0 && m.sigma > 0.0);
        let r = q * q;
        let ar = a * r;
        let kr = 1.0 / (c + a * r);
        s.pos = (s.pos * c + m.pos * ar) * kr;
        s.sigma = select(m.sigma, s.sigma * sqrt((c + a) * kr), s.sigma > 0.0);
        let n = s.nrm * c + m.nrm * ar;
        if (length(n) > 1e-12) {
            s.nrm = normalize(n);
        }
        let cs = unpack_colour(s.colour);
        let cm = unpack_colour(m.colour);
        let cf = clamp(round_pos3((cs * c + cm * a) * k), vec3<f32>(0.0), vec3<f32>(255.0));
        s.colour = u32(cf.x) | (u32(cf.y) << 8u) | (u32(cf.z) << 16u);
        s.radius = (s.radius * c + m.radius * a) * k;
        if (m.albedo > 0.0) {
            s.albedo = select(m.albedo, (s.albedo * c + m.albedo * a) * k, s.albedo > 0.0);
        }
    }
    s.conf = c + a;
    s.t = P.now;
    surf_a[i] = s;
    atomicAdd(&counters[SLOT_MERGED], 1u);
}

fn round_pos3(v: vec3<f32>) -> vec3<f32> {
    return floor(v + vec3<f32>(0.5));
}

// The clean pass (retain): stable, or seen within the lifetime.
@compute @workgroup_size(256)
fn keep(@builtin(global_invocation_id) g: vec3<u32>) {
    let i = g.x;
    if (i >= P.n_surfels) { return; }
    let s = surf_a[i];
    flags[i] = select(0u, 1u, s.conf >= P.stable || since(P.now, s.t) <= P.life);
}

// Exclusive prefix sum of flags[scan_base ..][.. scan_n] into offsets, in three passes.
fn scan_workgroup(l: u32) {
    for (var o = 1u; o < 256u; o = o * 2u) {
        var a = 0u;
        if (l >= o) { a = sh[l - o]; }
        workgroupBarrier();
        sh[l] = sh[l] + a;
        workgroupBarrier();
    }
}

@compute @workgroup_size(256)
fn scan_blocks(@builtin(global_invocation_id) g: vec3<u32>, @builtin(local_invocation_id) l: vec3<u32>, @builtin(workgroup_id) wg: vec3<u32>) {
    let i = g.x;
    var v = 0u;
    if (i < P.scan_n) { v = flags[P.scan_base + i]; }
    sh[l.x] = v;
    workgroupBarrier();
    scan_workgroup(l.x);
    if (i < P.scan_n) { offsets[P.scan_base + i] = sh[l.x] - v; }
    if (l.x == 255u) { blocks[wg.x] = sh[255]; }
}

@compute @workgroup_size(256)
fn scan_sums(@builtin(local_invocation_id) l: vec3<u32>) {
    let nb = (P.scan_n + 255u) / 256u;
    var carry = 0u;
    for (var base = 0u; base < nb; base = base + 256u) {
        let j = base + l.x;
        var v = 0u;
        if (j < nb) { v = blocks[j]; }
        sh[l.x] = v;
        workgroupBarrier();
        scan_workgroup(l.x);
        if (j < nb) { blocks[j] = carry + sh[l.x] - v; }
        carry = carry + sh[255];
        workgroupBarrier();
    }
    if (l.x == 0u) { atomicStore(&counters[P.scan_slot], carry); }
}

@compute @workgroup_size(256)
fn scan_add(@builtin(global_invocation_id) g: vec3<u32>, @builtin(workgroup_id) wg: vec3<u32>) {
    let i = g.x;
    if (i >= P.scan_n) { return; }
    offsets[P.scan_base + i] = offsets[P.scan_base + i] + blocks[wg.x];
}

// Order-preserving compaction of the kept surfels into surf_b.
@compute @workgroup_size(256)
fn compact(@builtin(global_invocation_id) g: vec3<u32>) {
    let i = g.x;
    if (i >= P.n_surfels) { return; }
    if (flags[i] == 1u) { surf_b[offsets[i]] = surf_a[i]; }
}

// New surfels (Measurement::to_surfel) after the kept ones, in pixel order.
@compute @workgroup_size(256)
fn append(@builtin(global_invocation_id) g: vec3<u32>) {
    let j = g.x;
    if (j >= P.n_meas) { return; }
    if (flags[P.add_base + j] == 0u) { return; }
    let m = meas[j];
    let at = atomicLoad(&counters[SLOT_KEPT]) + offsets[P.add_base + j];
    surf_b[at] = Surfel(m.pos, m.conf, m.nrm, m.radius, m.colour, P.now, P.now, m.albedo, m.sigma, 0.0, 0.0, 0.0);
}

// Active and stable counts of surf_b[.. kept + added].
@compute @workgroup_size(256)
fn count(@builtin(global_invocation_id) g: vec3<u32>) {
    let i = g.x;
    if (i >= atomicLoad(&counters[SLOT_KEPT]) + atomicLoad(&counters[SLOT_ADDED])) { return; }
    let s = surf_b[i];
    if (is_active(s)) { atomicAdd(&counters[SLOT_ACTIVE], 1u); }
    if (s.conf >= P.stable) { atomicAdd(&counters[SLOT_STABLE], 1u); }
}

// The prediction (surfel_cpu::predict): stable surfels of the set as discs, ray–disc
// intersection per pixel, an ε-z-buffer: the most confident disc within P.blend of the nearest
// wins (ties: the lowest index), in three passes (nearest depth; most confident; its index).
fn splat_include(s: Surfel) -> bool {
    return s.conf >= P.stable && (is_active(s) == (P.model_set == 0u));
}

// surfel_cpu::splat::conf_key: unsigned order = float order.
fn conf_key(c: f32) -> u32 {
    let b = bitcast<u32>(c);
    return select(b | 0x80000000u, ~b, (b >> 31u) == 1u);
}

struct Disc {
    p: vec3<f32>,
    n: vec3<f32>,
    np: f32,
    r2: f32,
    lo: vec2<i32>,
    hi: vec2<i32>,
    ok: bool,
}

// surfel_cpu::splat::Disc::new.
fn disc(s: Surfel) -> Disc {
    var d: Disc;
    d.ok = false;
    let p = to_cam(s.pos);
    if (p.z <= P.min_depth || p.z > P.max_depth) { return d; }
    d.p = p;
    d.n = rot_cam(s.nrm);
    d.np = dot(d.n, p);
    d.r2 = s.radius * s.radius;
    // surfel_cpu::splat::pixel_box: the projection of the disc's axis-aligned bounding box.
    let e = s.radius * sqrt(max(vec3<f32>(0.0), vec3<f32>(1.0) - d.n * d.n));
    let z_min = max(P.min_depth, 1e-6);
    let z_lo = max(p.z - e.z, z_min);
    let z_hi = max(p.z + e.z, z_min);
    let sx = box_span(p.x, e.x, z_lo, z_hi, p.z, P.fx, P.cx, i32(P.width));
    let sy = box_span(p.y, e.y, z_lo, z_hi, p.z, P.fy, P.cy, i32(P.height));
    d.lo = vec2<i32>(sx.x, sy.x);
    d.hi = vec2<i32>(sx.y, sy.y);
    d.ok = true;
    return d;
}

// One axis of surfel_cpu::splat::pixel_box: the first and last pixel, capped at 12 from the
// rounded centre and clipped to the image.
fn box_span(c: f32, e: f32, z_lo: f32, z_hi: f32, z: f32, f: f32, centre: f32, size: i32) -> vec2<i32> {
    let a = (c - e) / z_lo;
    let b = (c - e) / z_hi;
    let g = (c + e) / z_lo;
    let h = (c + e) / z_hi;
    let lo = min(min(a, b), min(g, h)) * f + centre;
    let hi = max(max(a, b), max(g, h)) * f + centre;
    let mid = i32(round_away(f * c / z + centre));
    let first = max(max(i32(ceil(lo - 1e-3)), mid - 12), 0);
    let last = min(min(i32(floor(hi + 1e-3)), mid + 12), size - 1);
    return vec2<i32>(first, last);
}

// surfel_cpu::splat::Disc::hit: the intersection depth, or -1 for a miss.
fn hit(d: Disc, x: i32, y: i32) -> f32 {
    let r = vec3<f32>((f32(x) - P.cx) / P.fx, (f32(y) - P.cy) / P.fy, 1.0);
    let nd = dot(d.n, r);
    if (abs(nd) < 1e-6) { return -1.0; }
    let t = d.np / nd;
    let e = r * t - d.p;
    if (t <= P.min_depth || t > P.max_depth || dot(e, e) > d.r2) { return -1.0; }
    return t;
}

// step 0: nearest depth; 1: most confident within P.blend of it, the confidence capped at
// P.stable when P.blend > 0 (surfel_cpu::splat::capped); 2: the lowest index of those.
fn splat(i: u32, step: u32) {
    let s = surf_a[i];
    if (!splat_include(s)) { return; }
    let d = disc(s);
    if (!d.ok) { return; }
    let key = conf_key(select(s.conf, min(s.conf, P.stable), P.blend > 0.0));
    for (var y = d.lo.y; y <= d.hi.y; y = y + 1) {
        for (var x = d.lo.x; x <= d.hi.x; x = x + 1) {
            let t = hit(d, x, y);
            if (t < 0.0) { continue; }
            let k = u32(y) * P.width + u32(x);
            let bits = bitcast<u32>(t);
            if (step == 0u) {
                if (bits < atomicLoad(&zdepth[k])) { atomicMin(&zdepth[k], bits); }
                continue;
            }
            if (t > bitcast<f32>(atomicLoad(&zdepth[k])) + P.blend) { continue; }
            if (step == 1u) {
                if (key > atomicLoad(&zconf[k])) { atomicMax(&zconf[k], key); }
            } else if (key == atomicLoad(&zconf[k])) {
                atomicMin(&zid[k], i);
            }
        }
    }
}

@compute @workgroup_size(256)
fn splat_depth(@builtin(global_invocation_id) g: vec3<u32>) {
    if (g.x >= P.n_surfels) { return; }
    splat(g.x, 0u);
}

@compute @workgroup_size(256)
fn splat_conf(@builtin(global_invocation_id) g: vec3<u32>) {
    if (g.x >= P.n_surfels) { return; }
    splat(g.x, 1u);
}

@compute @workgroup_size(256)
fn splat_id(@builtin(global_invocation_id) g: vec3<u32>) {
    if (g.x >= P.n_surfels) { return; }
    splat(g.x, 2u);
}

@compute @workgroup_size(256)
fn resolve(@builtin(global_invocation_id) g: vec3<u32>) {
    let k = g.x;
    if (k >= P.width * P.height) { return; }
    let i = atomicLoad(&zid[k]);
    var t = -1.0;
    if (i != EMPTY) { t = hit(disc(surf_a[i]), i32(k % P.width), i32(k / P.width)); }
    if (t < 0.0) {
        view[k] = ViewPixel(0.0, 0.0, 0.0, 0.0, 0u, 0.0, 0u, 0u, 0.0, 0.0);
        return;
    }
    let s = surf_a[i];
    let n = rot_cam(s.nrm);
    // surfel_cpu::splat::predicted_sigma.
    let sigma = s.sigma / sqrt(max(s.conf, 1.0));
    view[k] = ViewPixel(t, n.x, n.y, n.z, s.colour, s.conf, s.t0, s.t, s.albedo, sigma);
}
