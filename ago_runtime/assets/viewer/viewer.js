// The 3-D occupancy viewer of `ago ... --html` (ago_runtime/pictures/html_viewer.py writes the data it reads).
// Voxels are instanced unit cubes in unlit class colours (top faces exactly the class colour, sides darker), one
// three.js renderer per view (prediction, ground truth) sharing one camera. window.agoViewer is a small API for
// tests and people: counts(), setVisible(name, on), setMode(name), setThreshold(value), pick(view, x, y).
// URL fragment (tests): #hide=car,truck&mode=unexplained&threshold=0.5 applies those settings at load (click=car: a
// click on the legend entry); pick=0.5,0.5
// describes the voxel under that point (fractions of the first view's width and height) in the result.
"use strict";
(function () {
  const T = THREE;
  T.ColorManagement.enabled = false;             // class colours reach the screen unchanged
  const D = JSON.parse(document.getElementById("ago-data").textContent);
  const hash = new URLSearchParams(location.hash.slice(1));
  const $ = (id) => document.getElementById(id);
  const EGO_RGB = [64, 64, 64], BOX_RGB = [150, 150, 150], BACKGROUND = 0xffffff;
  // per face of BoxGeometry (+x, -x, +y, -y, +z, -z): tops keep the exact colour, sides darker
  const FACE_SHADE = [0.8, 0.8, 0.65, 0.65, 1.0, 0.5];

  function bytes(b64) {
    const s = atob(b64), a = new Uint8Array(s.length);
    for (let i = 0; i < s.length; i++) a[i] = s.charCodeAt(i);
    return a;
  }

  function voxelIndices(v) {               // sorted flat C-order indices of the drawn voxels
    const raw = bytes(v.index);
    if (v.index_kind === "uint32") return new Uint32Array(raw.buffer);
    const idx = new Uint32Array(v.count);  // bitmask, little bit order (numpy packbits bitorder="little")
    let n = 0;
    for (let b = 0; b < raw.length; b++) {
      let x = raw[b];
      while (x) { const low = x & -x; idx[n++] = b * 8 + (31 - Math.clz32(low)); x ^= low; }
    }
    return idx;
  }

  function decodeView(v) {
    const V = { title: v.title, shape: v.shape, min: v.range_min, size: v.voxel_size, names: v.classes.map((c) => c.name),
                rgb: v.classes.map((c) => c.color), idx: voxelIndices(v), labels: bytes(v.labels), scalars: {},
                occupied: v.occupied, voxels: v.voxels };
    V.count = V.idx.length;
    for (const s of v.scalars) {
      const q = new Uint16Array(bytes(s.data).buffer), vals = new Float32Array(q.length), k = (s.hi - s.lo) / 65535;
      for (let i = 0; i < q.length; i++) vals[i] = s.lo + q[i] * k;
      V.scalars[s.name] = { name: s.name, unit: s.unit, lo: s.lo, hi: s.hi, threshold: s.threshold, values: vals };
    }
    return V;
  }

  const views = D.views.map(decodeView);
  const classOrder = [], classRGB = {};
  for (const V of views) V.names.forEach((n, c) => { if (!(n in classRGB)) { classOrder.push(n); classRGB[n] = V.rgb[c]; } });
  const scalarNames = [];
  for (const V of views) for (const n in V.scalars) if (!scalarNames.includes(n)) scalarNames.push(n);
  const state = { visible: {}, mode: "classes", threshold: {} };
  classOrder.forEach((n) => { state.visible[n] = true; });
  for (const V of views) for (const n in V.scalars) if (!(n in state.threshold)) state.threshold[n] = V.scalars[n].threshold;

  // ---------------------------------------------------------------------------------- the page around the views
  $("title").textContent = D.title;
  document.title = D.title;
  for (const note of D.notes) { const d = document.createElement("div"); d.textContent = "note: " + note; $("notes").appendChild(d); }

  function heatRGB(t) {                    // black - purple - red - orange - yellow (like inferno), t in 0..1
    const stops = [[0, 0, 4], [87, 16, 110], [188, 55, 84], [249, 142, 9], [252, 255, 164]];
    t = Math.min(1, Math.max(0, t)) * (stops.length - 1);
    const i = Math.min(stops.length - 2, Math.floor(t)), f = t - i;
    return stops[i].map((a, j) => Math.round(a + (stops[i + 1][j] - a) * f));
  }

  // ---------------------------------------------------------------------------------- three.js scene per view
  function shadedBox(sx, sy, sz) {
    const g = new T.BoxGeometry(sx, sy, sz);
    const shade = new Float32Array(g.attributes.position.count * 3);
    g.groups.forEach((grp, face) => {
      for (let i = grp.start; i < grp.start + grp.count; i++) {
        const v = g.index.array[i];
        shade[3 * v] = shade[3 * v + 1] = shade[3 * v + 2] = FACE_SHADE[face];
      }
    });
    g.setAttribute("color", new T.Float32BufferAttribute(shade, 3));
    return g;
  }
  const rgbColor = (c) => new T.Color(c[0] / 255, c[1] / 255, c[2] / 255);

  function gridBox(V) {
    const a = V.min, b = V.min.map((m, i) => m + V.size[i] * V.shape[i]), p = [];
    const corner = (i) => [i & 1 ? b[0] : a[0], i & 2 ? b[1] : a[1], i & 4 ? b[2] : a[2]];
    for (let i = 0; i < 8; i++) for (const bit of [1, 2, 4]) if (!(i & bit)) p.push(...corner(i), ...corner(i | bit));
    const g = new T.BufferGeometry();
    g.setAttribute("position", new T.Float32BufferAttribute(p, 3));
    return new T.LineSegments(g, new T.LineBasicMaterial({ color: rgbColor(BOX_RGB) }));
  }

  function egoCar() {                      // the ego frame's origin is the rear axle on the ground
    const car = new T.InstancedMesh(shadedBox(4.6, 1.9, 1.6), new T.MeshBasicMaterial({ vertexColors: true, color: rgbColor(EGO_RGB) }), 1);
    car.setMatrixAt(0, new T.Matrix4().makeTranslation(1.3, 0, 0.8));
    const arrow = new T.BufferGeometry();
    arrow.setAttribute("position", new T.Float32BufferAttribute([3.6, 0, 0.8, 7, 0, 0.8, 7, 0, 0.8, 6, 0.6, 0.8, 7, 0, 0.8, 6, -0.6, 0.8], 3));
    return [car, new T.LineSegments(arrow, new T.LineBasicMaterial({ color: rgbColor(EGO_RGB) }))];
  }

  const camera = new T.PerspectiveCamera(45, 1, 0.1, 2000);
  camera.up.set(0, 0, 1);                  // ego z is up
  const target = new T.Vector3(6, 0, 0);
  let renderers = [];
  let webgl = true;

  function buildView(V, k) {
    const el = document.createElement("div");
    el.className = "view";
    el.innerHTML = '<div class="vt"></div><canvas></canvas><div class="empty"></div>';
    el.querySelector(".vt").textContent = V.title;
    $("views").appendChild(el);
    V.el = el;
    V.canvas = el.querySelector("canvas");
    if (V.occupied === 0) {
      const e = el.querySelector(".empty");
      e.textContent = "all " + V.voxels.toLocaleString("en") + " voxels are free: nothing to draw";
      e.style.display = "flex";
    }
    try {
      V.renderer = new T.WebGLRenderer({ canvas: V.canvas, antialias: false, preserveDrawingBuffer: true });
    } catch (err) {
      webgl = false;
      const e = el.querySelector(".empty");
      e.textContent = "this browser gives no WebGL: the 3-D view cannot be drawn (" + err.message + ")";
      e.style.display = "flex";
      return;
    }
    V.renderer.outputColorSpace = T.LinearSRGBColorSpace;
    V.renderer.setClearColor(BACKGROUND, 1);
    V.renderer.setPixelRatio(Math.min(window.devicePixelRatio || 1, 2));
    V.scene = new T.Scene();
    const cube = shadedBox(1, 1, 1);
    V.mesh = new T.InstancedMesh(cube, new T.MeshBasicMaterial({ vertexColors: true }), Math.max(1, V.count));
    V.mesh.instanceColor = new T.InstancedBufferAttribute(new Float32Array(Math.max(1, V.count) * 3), 3);
    V.mesh.frustumCulled = false;
    V.mesh.count = 0;
    V.shown = new Uint8Array(V.count);
    V.order = new Uint32Array(V.count);     // instance slot -> voxel number
    V.scene.add(V.mesh, gridBox(V), ...egoCar());
    V.controls = new T.OrbitControls(camera, V.canvas);
    V.controls.target = target;             // one camera, one target: the views turn together
    V.controls.addEventListener("change", renderAll);
    V.canvas.addEventListener("pointermove", (ev) => hover(V, ev));
    V.canvas.addEventListener("pointerleave", () => { $("tip").style.display = "none"; });
    renderers.push(V);
  }

  function centre(V, i) {
    const [, Y, Z] = V.shape, z = i % Z, y = Math.floor(i / Z) % Y, x = Math.floor(i / (Y * Z));
    return [x, y, z].map((c, a) => V.min[a] + V.size[a] * (c + 0.5)).concat([x, y, z]);
  }

  function rebuild(V) {
    if (!V.mesh) return;
    const sc = V.scalars[state.mode] || null;
    const thr = sc ? state.threshold[state.mode] : 0;
    const m = V.mesh.instanceMatrix.array, col = V.mesh.instanceColor.array, [sx, sy, sz] = V.size;
    let n = 0;
    for (let k = 0; k < V.count; k++) {
      V.shown[k] = 0;
      const c = V.labels[k];
      if (!state.visible[V.names[c]]) continue;
      let rgb = V.rgb[c];
      if (sc) {
        const v = sc.values[k];
        if (v < thr) continue;
        rgb = heatRGB((v - thr) / ((sc.hi - thr) || 1));   // the whole scale over what is shown
      }
      const p = centre(V, V.idx[k]), o = 16 * n;
      m.fill(0, o, o + 16);
      m[o] = sx; m[o + 5] = sy; m[o + 10] = sz; m[o + 12] = p[0]; m[o + 13] = p[1]; m[o + 14] = p[2]; m[o + 15] = 1;
      col[3 * n] = rgb[0] / 255; col[3 * n + 1] = rgb[1] / 255; col[3 * n + 2] = rgb[2] / 255;
      V.shown[k] = 1;
      V.order[n++] = k;
    }
    V.mesh.count = n;
    V.mesh.instanceMatrix.needsUpdate = true;
    V.mesh.instanceColor.needsUpdate = true;
  }

  function resize() {
    for (const V of renderers) {
      const w = Math.max(1, V.el.clientWidth), h = Math.max(1, V.el.clientHeight);
      V.renderer.setSize(w, h, false);
      camera.aspect = w / h;
    }
    camera.updateProjectionMatrix();
  }

  function renderAll() { for (const V of renderers) V.renderer.render(V.scene, camera); }

  function update() { for (const V of renderers) rebuild(V); renderAll(); refreshSide(); }

  // ---------------------------------------------------------------------------------- hover: ray through the grid
  function lookup(V, flat) {               // voxel number of a flat index, or -1
    let lo = 0, hi = V.count - 1;
    while (lo <= hi) {
      const mid = (lo + hi) >> 1, v = V.idx[mid];
      if (v === flat) return mid;
      if (v < flat) lo = mid + 1; else hi = mid - 1;
    }
    return -1;
  }

  function pick(V, px, py) {               // the first shown voxel under canvas pixel (px, py), or -1
    const r = V.canvas.getBoundingClientRect();
    const ray = new T.Raycaster();
    ray.setFromCamera(new T.Vector2((px / r.width) * 2 - 1, -(py / r.height) * 2 + 1), camera);
    const S = V.shape, o = [], d = [];
    const org = ray.ray.origin.toArray(), dir = ray.ray.direction.toArray();
    for (let a = 0; a < 3; a++) { o.push((org[a] - V.min[a]) / V.size[a]); d.push(dir[a] / V.size[a]); }
    let t0 = 0, t1 = Infinity;
    for (let a = 0; a < 3; a++) {
      if (Math.abs(d[a]) < 1e-12) { if (o[a] < 0 || o[a] > S[a]) return -1; continue; }
      let ta = -o[a] / d[a], tb = (S[a] - o[a]) / d[a];
      if (ta > tb) [ta, tb] = [tb, ta];
      t0 = Math.max(t0, ta); t1 = Math.min(t1, tb);
    }
    if (t0 > t1) return -1;
    const cell = [], step = [], tMax = [], tDelta = [];
    for (let a = 0; a < 3; a++) {
      cell.push(Math.min(S[a] - 1, Math.max(0, Math.floor(o[a] + d[a] * (t0 + 1e-9)))));
      step.push(d[a] > 0 ? 1 : -1);
      tMax.push(Math.abs(d[a]) < 1e-12 ? Infinity : (cell[a] + (d[a] > 0 ? 1 : 0) - o[a]) / d[a]);
      tDelta.push(Math.abs(d[a]) < 1e-12 ? Infinity : Math.abs(1 / d[a]));
    }
    for (let guard = 0; guard < S[0] + S[1] + S[2] + 3; guard++) {
      const k = lookup(V, (cell[0] * S[1] + cell[1]) * S[2] + cell[2]);
      if (k >= 0 && V.shown[k]) return k;
      const a = tMax[0] < tMax[1] ? (tMax[0] < tMax[2] ? 0 : 2) : (tMax[1] < tMax[2] ? 1 : 2);
      cell[a] += step[a];
      if (cell[a] < 0 || cell[a] >= S[a]) return -1;
      tMax[a] += tDelta[a];
    }
    return -1;
  }

  function describe(V, k) {
    const p = centre(V, V.idx[k]);
    const lines = [V.names[V.labels[k]] + "   (" + V.title + ")",
                   "x " + p[0].toFixed(1) + " m, y " + p[1].toFixed(1) + " m, z " + p[2].toFixed(1) + " m",
                   "voxel [" + p[3] + ", " + p[4] + ", " + p[5] + "]"];
    for (const n in V.scalars) { const s = V.scalars[n]; lines.push(n + " " + s.values[k].toFixed(3) + (s.unit ? " " + s.unit : "")); }
    return lines.join("\n");
  }

  function hover(V, ev) {
    const r = V.canvas.getBoundingClientRect(), k = pick(V, ev.clientX - r.left, ev.clientY - r.top), tip = $("tip");
    if (k < 0) { tip.style.display = "none"; return; }
    tip.textContent = describe(V, k);
    tip.style.left = (ev.clientX + 14) + "px";
    tip.style.top = (ev.clientY + 14) + "px";
    tip.style.display = "block";
  }

  // ---------------------------------------------------------------------------------- legend and heat controls
  function counts() {                      // what each view drew: class name -> instances
    const out = {};
    for (const V of views) {
      const c = {};
      if (V.mesh) for (let n = 0; n < V.mesh.count; n++) { const name = V.names[V.labels[V.order[n]]]; c[name] = (c[name] || 0) + 1; }
      out[V.title] = c;
    }
    return out;
  }

  function fileCounts(V) {
    const c = {};
    for (let k = 0; k < V.count; k++) { const name = V.names[V.labels[k]]; c[name] = (c[name] || 0) + 1; }
    return c;
  }

  const legendRows = {};
  function buildSide() {
    const per = views.map(fileCounts);
    for (const name of classOrder) {
      const n = per.map((c) => c[name] || 0);
      if (n.every((x) => x === 0)) continue;
      const row = document.createElement("div");
      row.className = "entry";
      row.title = "click: hide / show " + name;
      row.innerHTML = '<span class="sw"></span><span class="name"></span><span class="n"></span>';
      row.querySelector(".sw").style.background = "rgb(" + classRGB[name].join(",") + ")";
      row.querySelector(".name").textContent = name;
      row.querySelector(".n").textContent = n.map((x) => x.toLocaleString("en")).join(" / ");
      row.addEventListener("click", () => { api.setVisible(name, !state.visible[name]); });
      $("legend").appendChild(row);
      legendRows[name] = row;
    }
    $("all").onclick = () => { classOrder.forEach((n) => { state.visible[n] = true; }); update(); };
    $("none").onclick = () => { classOrder.forEach((n) => { state.visible[n] = false; }); update(); };
    for (const n of scalarNames) { const o = document.createElement("option"); o.value = n; o.textContent = n; $("mode").appendChild(o); }
    $("mode").onchange = () => api.setMode($("mode").value);
    $("threshold").oninput = () => {
      const s = scalarOf(state.mode);
      api.setThreshold(s.lo + (s.hi - s.lo) * $("threshold").value / 1000);
    };
    const stops = [0, 0.25, 0.5, 0.75, 1].map((t) => "rgb(" + heatRGB(t).join(",") + ")");
    $("bar").style.background = "linear-gradient(to right," + stops.join(",") + ")";
  }

  function scalarOf(name) { for (const V of views) if (V.scalars[name]) return V.scalars[name]; return null; }

  function refreshSide() {
    for (const name in legendRows) legendRows[name].classList.toggle("off", !state.visible[name]);
    const s = scalarOf(state.mode);
    $("heat").style.display = s ? "block" : "none";
    $("mode").value = state.mode;
    if (s) {
      const thr = state.threshold[state.mode];
      $("lo").textContent = thr.toPrecision(3);
      $("hi").textContent = s.hi.toPrecision(3);
      $("tval").textContent = thr.toPrecision(3) + (s.unit ? " " + s.unit : "");
      $("threshold").value = Math.round(1000 * (thr - s.lo) / ((s.hi - s.lo) || 1));
    }
  }

  function layoutCams() {
    if (!D.images.length) { $("cams").style.display = "none"; return; }
    $("cams").style.gridTemplateColumns = "repeat(" + D.image_columns + ", 1fr)";
    for (const im of D.images) {
      const f = document.createElement("figure");
      f.innerHTML = "<img><figcaption></figcaption>";
      f.querySelector("img").src = "data:image/jpeg;base64," + im.jpeg;
      f.querySelector("img").alt = im.name;
      f.querySelector("figcaption").textContent = im.name;
      $("cams").appendChild(f);
    }
  }

  const api = {
    views: views.map((V) => V.title),
    counts,
    setVisible(name, on) { if (!(name in state.visible)) throw new Error("no class " + name); state.visible[name] = !!on; update(); },
    setMode(name) { if (name !== "classes" && !scalarOf(name)) throw new Error("no volume " + name); state.mode = name; update(); },
    setThreshold(t) { if (state.mode !== "classes") { state.threshold[state.mode] = Number(t); update(); } },
    pick(view, x, y) { const V = views[view]; const k = pick(V, x, y); return k < 0 ? null : describe(V, k); },
    state,
  };
  window.agoViewer = api;

  // ---------------------------------------------------------------------------------- start
  layoutCams();
  views.forEach(buildView);
  buildSide();
  {                                          // from behind-right and above, the whole grid in sight
    const G = views[0], ext = G.shape.map((n, a) => n * G.size[a]), L = Math.max(ext[0], ext[1]) / 2;
    target.set(G.min[0] + ext[0] / 2 + 0.08 * L, G.min[1] + ext[1] / 2, G.min[2]);
    camera.position.set(target.x - 1.45 * L, target.y - 1.1 * L, target.z + 1.35 * L);
    camera.far = 40 * L;
    camera.lookAt(target);
  }
  resize();
  for (const V of renderers) V.controls.update();
  update();
  // the URL fragment, through the same paths as the page's controls
  for (const n of (hash.get("hide") || "").split(",")) if (n in state.visible) api.setVisible(n, false);
  for (const n of (hash.get("click") || "").split(",")) if (n in legendRows) legendRows[n].click();
  if (hash.get("mode") && (hash.get("mode") === "classes" || scalarOf(hash.get("mode")))) api.setMode(hash.get("mode"));
  else if (scalarOf(D.mode)) api.setMode(D.mode);
  if (hash.get("threshold")) api.setThreshold(hash.get("threshold"));
  window.addEventListener("resize", () => { resize(); renderAll(); });
  const rects = views.map((V) => { const r = V.canvas.getBoundingClientRect(); return [r.left, r.top, r.width, r.height].map(Math.round); });
  let picked = null;
  if (hash.get("pick") && views[0].renderer) {
    const [fx, fy] = hash.get("pick").split(",").map(Number), r = views[0].canvas.getBoundingClientRect();
    picked = api.pick(0, fx * r.width, fy * r.height);
  }
  $("ago-result").textContent = JSON.stringify({
    webgl, pick: picked, counts: counts(), rects, notes: D.notes, mode: state.mode,
    empty: views.filter((V) => V.occupied === 0).map((V) => V.title),
    hidden: classOrder.filter((n) => !state.visible[n]),
  });
})();
