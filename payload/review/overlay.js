// The review's overlay on meshcat's viewer: title, legend, labels placed by a layout pass
// with leader lines, the trial phase, an error banner, the chase camera, live updates, and
// the 3-D view fitted below the title (a design review's bays and payload beside the legend).
// Reads window.viewer (meshcat's Viewer). Data: see payload/review/page.py.
(function () {
  "use strict";
  const pane = document.getElementById("meshcat-pane");
  const layer = document.createElement("div");
  layer.id = "payload-overlay";
  pane.appendChild(layer);
  const svg = document.createElementNS("http://www.w3.org/2000/svg", "svg");
  svg.id = "payload-leaders";
  layer.appendChild(svg);
  // the title (with the verdict) and the error banner in one column: a verdict that
  // wraps pushes the banner down instead of lying under it
  const head = div("payload-head", layer);
  const title = div("payload-title", head);
  const legend = div("payload-legend", layer);
  const phase = div("payload-phase", layer);
  const error = div("payload-error", head);
  // the most of the pane's height the top boxes take from the view (a tiny window keeps one)
  const MAX_TOP_SHARE = 0.5;
  // the free margin the subject keeps to the title, the legend and the pane's edges [px]
  const SUBJECT_PAD = 12;
  const state = {
    labels: [], phases: [], follow: null, chase: true, views: {}, clear: [], subject: [],
    version: -1,
  };

  function div(id, parent) {
    const el = document.createElement("div");
    if (id) el.id = id;
    parent.appendChild(el);
    return el;
  }

  function b64bytes(s) {
    const bin = atob(s);
    const out = new Uint8Array(bin.length);
    for (let i = 0; i < bin.length; i++) out[i] = bin.charCodeAt(i);
    return out;
  }

  function names(path) {
    return path.split("/").filter((x) => x.length > 0);
  }

  function node(path) {
    let n = viewer.scene_tree;
    for (const name of names(path)) {
      n = n.children[name];
      if (n === undefined) return null;
    }
    return n.object;
  }

  function shown(obj) {
    for (let o = obj; o; o = o.parent) if (!o.visible) return false;
    return true;
  }

  function setOverlay(o) {
    // the browser's tab, as the server words it (scene.tab_title; an older overlay: none)
    document.title = o.tab || "payload review";
    title.innerHTML = "";
    div(null, title).textContent = o.title || "";
    const sub = div(null, title);
    sub.className = "payload-subtitle";
    // a verdict (the design review's pass or fail) is drawn large, bold, in its colour
    if (o.outcome) sub.classList.add("payload-verdict", `payload-verdict-${o.outcome}`);
    sub.textContent = o.subtitle || "";
    legend.innerHTML = "";
    for (const [colour, text] of o.legend || []) {
      const row = div(null, legend);
      row.className = "payload-legend-row";
      row.dataset.colour = colour.toLowerCase();
      const sw = div(null, row);
      sw.className = "payload-swatch";
      sw.style.background = colour;
      const t = document.createElement("span");
      t.textContent = text;
      row.appendChild(t);
    }
    for (const lab of state.labels) {
      lab.el.remove();
      lab.line.remove();
    }
    state.labels = (o.labels || []).map(([anchor, text]) => {
      const el = div(null, layer);
      el.className = "payload-label";
      el.textContent = text;
      const line = document.createElementNS("http://www.w3.org/2000/svg", "line");
      svg.appendChild(line);
      return { anchor, el, line };
    });
    state.phases = o.phases || [];
    state.follow = o.follow || null;
    state.views = o.views || {};
    state.clear = o.clear || [];
    state.subject = o.subject || [];
    if (state.follow && !state.controlAdded) {
      viewer.set_control("whole station view", "() => payloadReview.toggleView()");
      state.controlAdded = true;
    }
    if (!state.placed) {
      // the first scene sets the view; a rebuild keeps the one the user has
      if (state.follow) state.chase = true;
      placeCamera();
      state.placed = true;
    }
  }

  function placeCamera() {
    const key = state.follow && !state.chase ? "station" : "default";
    const p = state.views[key];
    if (!p) return;
    const cam = viewer.scene_tree.find(["Cameras", "default", "rotated", "<object>"]);
    cam.set_property("position", [p[0], p[2], -p[1]]);
    if (viewer.controls) viewer.controls.target.set(0, 0, 0);
    viewer.set_dirty();
  }

  function follow() {
    if (!state.follow) return;
    const [rootPath, vehiclePath, centre] = state.follow;
    const root = node(rootPath);
    const vehicle = node(vehiclePath);
    if (!root || !vehicle) return;
    const c = state.chase ? vehicle.position : { x: centre[0], y: centre[1], z: centre[2] };
    const p = root.position;
    if (p.x === -c.x && p.y === -c.y && p.z === -c.z) return;
    p.set(-c.x, -c.y, -c.z);
    root.updateMatrixWorld(true);
    // meshcat renders before this runs (and, paused, only when dirty): draw the moved root
    viewer.set_dirty();
  }

  function animationTime() {
    const a = viewer.animator;
    return a && a.actions.length ? Math.max(...a.actions.map((x) => x.time)) : 0;
  }

  function showPhase() {
    // a replay's title wraps short of the phase box at the top right (a long subtitle ran
    // under it in a narrow window)
    layer.classList.toggle("payload-has-phase", state.phases.length > 0);
    if (!state.phases.length) {
      phase.style.display = "none";
      return;
    }
    const t = animationTime();
    let now = state.phases[0];
    for (const p of state.phases) if (p[1] <= t + 1e-9) now = p;
    phase.style.display = "block";
    phase.textContent = `phase: ${now[0]}   t = ${t.toFixed(1)} s`;
  }

  // Screen box of a shown node's meshes (the 8 corners of its world bounds, projected), or
  // null: not shown, empty, or partly behind the camera (no box bounds it there).
  function screenBox(path, cam, w, h) {
    const obj = node(path);
    if (!obj || !shown(obj)) return null;
    obj.updateWorldMatrix(true, true);
    const box = new MeshCat.THREE.Box3().setFromObject(obj);
    if (box.isEmpty()) return null;
    const [lo, hi] = [box.min, box.max];
    let x0 = Infinity, y0 = Infinity, x1 = -Infinity, y1 = -Infinity;
    for (let i = 0; i < 8; i++) {
      const p = new MeshCat.THREE.Vector3(
        i & 1 ? hi.x : lo.x, i & 2 ? hi.y : lo.y, i & 4 ? hi.z : lo.z);
      p.project(cam);
      if (p.z > 1 || p.z < -1) return null;
      const x = ((p.x + 1) / 2) * w;
      const y = ((1 - p.y) / 2) * h;
      x0 = Math.min(x0, x); y0 = Math.min(y0, y); x1 = Math.max(x1, x); y1 = Math.max(y1, y);
    }
    return { x: x0, y: y0, w: x1 - x0, h: y1 - y0 };
  }

  // The subject's box (the design review's bays and stowed payload: world points about the
  // camera's target) as the default view frames it, in the camera's frame: [0, 1] across
  // (u) and down (v). The default view's camera, not the user's: an orbit or a zoom moves
  // the subject on screen, and the fit below follows the overlay, not the user.
  function subjectBox(w, h) {
    const pts = state.subject;
    const p = state.views.default;
    if (!pts.length || !p) return null;
    const key = JSON.stringify([w, h, viewer.camera.fov, p, pts]);
    if (state.subjectBox && state.subjectBox.key === key) return state.subjectBox.box;
    const T = MeshCat.THREE;
    const cam = new T.PerspectiveCamera(viewer.camera.fov, w / h, 0.001, 1000);
    cam.up.set(0, 0, 1);
    cam.position.set(p[0], p[1], p[2]);
    cam.lookAt(0, 0, 0);
    cam.updateMatrixWorld();
    const b = { u0: Infinity, v0: Infinity, u1: -Infinity, v1: -Infinity };
    for (const q of pts) {
      const n = new T.Vector3(q[0], q[1], q[2]).project(cam);
      const u = (n.x + 1) / 2;
      const v = (1 - n.y) / 2;
      b.u0 = Math.min(b.u0, u); b.v0 = Math.min(b.v0, v);
      b.u1 = Math.max(b.u1, u); b.v1 = Math.max(b.v1, v);
    }
    state.subjectBox = { key, box: b };  // the same every frame until the page or scene changes
    return b;
  }

  // Where the camera's frame goes (setViewOffset's full size and offset) so that the subject
  // lies in the larger free part of the pane: below the top boxes and above the legend, or
  // right of the legend; centred there, made smaller only when it does not fit (never
  // larger). null: no subject (a trial replay).
  function subjectFit(w, h, top) {
    const b = subjectBox(w, h);
    if (!b) return null;
    const pane0 = pane.getBoundingClientRect();
    const rooms = [{ x0: 0, y0: top, x1: w, y1: h }];
    if (legend.offsetParent !== null && legend.childElementCount) {
      const r = legend.getBoundingClientRect();
      rooms[0].y1 = r.top - pane0.top;
      rooms.push({ x0: r.right - pane0.left, y0: top, x1: w, y1: h });
    }
    let best = null;
    for (const r of rooms) {
      const rw = r.x1 - r.x0 - 2 * SUBJECT_PAD;
      const rh = r.y1 - r.y0 - 2 * SUBJECT_PAD;
      if (rw <= 0 || rh <= 0) continue;
      const s = Math.min(1, rw / ((b.u1 - b.u0) * w), rh / ((b.v1 - b.v0) * h));
      if (best === null || s > best.s + 1e-9) best = { s, r };
    }
    if (best === null) return null;
    const { s, r } = best;
    const fw = w * s;
    const fh = h * s;
    return { fw, fh, x: ((b.u0 + b.u1) / 2) * fw - (r.x0 + r.x1) / 2,
      y: ((b.v0 + b.v1) / 2) * fh - (r.y0 + r.y1) / 2 };
  }

  // The 3-D view is drawn in the part of the pane the overlay's boxes leave free: what the
  // camera frames (the whole pane's view, as the review set it) is scaled by three.js's view
  // offset into the pane below the top boxes (the title with its verdict and the error
  // banner, the trial phase) and centred there; a design review's subject (the bays and the
  // stowed payload) is fitted beside the legend too (subjectFit). A long verdict (a failing
  // design's) wrapped over the top of Astrobee's body; with the overlay hidden the view is
  // the whole pane's.
  function fitView() {
    const cam = viewer.camera;
    const w = pane.clientWidth;
    const h = pane.clientHeight;
    if (!cam || !cam.setViewOffset || !w || !h) return;
    const paneTop = pane.getBoundingClientRect().top;
    let top = 0;
    for (const e of [head, phase]) {
      if (e.offsetParent !== null) top = Math.max(top, e.getBoundingClientRect().bottom - paneTop);
    }
    top = Math.min(Math.max(top, 0), h * MAX_TOP_SHARE);
    const v = cam.view;
    if (top === 0) {
      if (v && v.enabled) {
        cam.clearViewOffset();
        viewer.set_dirty();
      }
      return;
    }
    // else the camera's frame (its field of view) made s times the pane, its top row on the
    // free part's top, centred across; the pane shows that and the margins beside it
    const s = (h - top) / h;
    const fit = subjectFit(w, h, top) || { fw: w * s, fh: h * s, x: (w * s - w) / 2, y: -top };
    const { fw, fh, x, y } = fit;
    if (v && v.enabled && v.fullWidth === fw && v.fullHeight === fh && v.offsetX === x
      && v.offsetY === y && v.width === w && v.height === h) return;
    cam.setViewOffset(fw, fh, x, y, w, h);
    viewer.set_dirty();
  }

  function overlaps(a, b) {
    return a.x < b.x + b.w && b.x < a.x + a.w && a.y < b.y + b.h && b.y < a.y + a.h;
  }

  function layout() {
    const cam = viewer.camera;
    const w = pane.clientWidth;
    const h = pane.clientHeight;
    cam.updateMatrixWorld();
    const items = [];
    for (const lab of state.labels) {
      const obj = node(lab.anchor);
      lab.el.style.display = "none";
      lab.line.style.display = "none";
      if (!obj || !shown(obj)) continue;
      const p = obj.getWorldPosition(new obj.position.constructor());
      p.project(cam);
      if (p.z > 1 || p.z < -1 || Math.abs(p.x) > 1 || Math.abs(p.y) > 1) continue;
      items.push({ lab, x: ((p.x + 1) / 2) * w, y: ((1 - p.y) / 2) * h });
    }
    // fixed boxes labels must not cover: title, legend, phase, meshcat's controls
    const fixed = [title, legend, phase, error].filter((e) => e.offsetParent !== null);
    const placed = fixed.map((e) => {
      const r = e.getBoundingClientRect();
      return { x: r.left, y: r.top, w: r.width, h: r.height };
    });
    // meshcat's controls (dat.GUI): as large as they are now, open or closed
    const gui = document.querySelector(".dg.main");
    const g = gui && gui.offsetParent !== null ? gui.getBoundingClientRect() : null;
    placed.push(g && g.width > 0 ? { x: g.left, y: g.top, w: g.width, h: g.height }
      : { x: w - 250, y: 0, w: 250, h: 24 });
    // what the labels must not hide (a replay's vehicle, payload and CTB), as projected now
    for (const path of state.clear) {
      const b = screenBox(path, cam, w, h);
      if (b) placed.push(b);
    }
    items.sort((a, b) => a.y - b.y);
    for (const it of items) {
      const el = it.lab.el;
      el.style.display = "block";
      const bw = el.offsetWidth;
      const bh = el.offsetHeight;
      let best = null;
      for (let k = 0; k < 60 && best === null; k++) {
        for (const side of [1, -1]) {
          for (const dir of [-1, 1]) {
            const x = side > 0 ? it.x + 28 : it.x - 28 - bw;
            const y = it.y - bh / 2 + dir * k * (bh / 2 + 2);
            const box = { x, y, w: bw, h: bh };
            if (x < 0 || y < 0 || x + bw > w || y + bh > h) continue;
            if (placed.every((b) => !overlaps(box, b))) {
              best = box;
              break;
            }
          }
          if (best !== null) break;
        }
      }
      if (best === null) {
        el.style.display = "none";
        continue;
      }
      placed.push(best);
      el.style.left = `${best.x}px`;
      el.style.top = `${best.y}px`;
      const ex = best.x > it.x ? best.x : best.x + bw;
      const line = it.lab.line;
      line.style.display = "block";
      line.setAttribute("x1", it.x);
      line.setAttribute("y1", it.y);
      line.setAttribute("x2", ex);
      line.setAttribute("y2", best.y + bh / 2);
    }
  }

  function frame() {
    follow();
    showPhase();
    fitView();
    layout();
    requestAnimationFrame(frame);
  }

  function armAnimation() {
    // meshcat loads an animation that does not autoplay with its actions never started, and
    // three.js's mixer skips such actions: seeking (the time slider) then moved nothing until
    // Play was pressed once. Start them with the animator's clock stopped: the page stays
    // paused where it is, and the slider shows any time of the animation.
    const a = viewer.animator;
    if (!a || a.playing) return;
    for (const x of a.actions) if (!x.isScheduled()) x.play();
  }

  function apply(update) {
    for (const c of update.commands || []) viewer.handle_command_bytearray(b64bytes(c));
    armAnimation();
    if (update.overlay) setOverlay(update.overlay);
    error.textContent = update.error || "";
    error.style.display = update.error ? "block" : "none";
    if (update.version !== undefined) state.version = update.version;
    viewer.set_dirty();
    window.payloadReady = true;
  }

  async function poll() {
    try {
      const r = await fetch(`update?have=${state.version}`, { cache: "no-store" });
      if (r.ok) {
        const u = await r.json();
        // another review now serves this address (its versions count from 0 too): start
        // over from its page rather than keep a scene it does not know of
        if (state.session === undefined) state.session = u.session;
        else if (u.session !== state.session) return location.reload();
        if (u.version !== state.version || (u.error || "") !== error.textContent) apply(u);
      }
    } catch (e) {
      error.textContent = "the review server stopped";
      error.style.display = "block";
    }
    setTimeout(poll, 250);
  }

  window.payloadReview = {
    apply,
    state,
    get error() {
      return error.style.display === "none" ? "" : error.textContent;
    },
    toggleView() {
      state.chase = !state.chase;
      placeCamera();
    },
    // screen rectangles of the shown labels, for tests
    labelBoxes() {
      return state.labels
        .filter((l) => l.el.style.display !== "none")
        .map((l) => {
          const r = l.el.getBoundingClientRect();
          return { text: l.el.textContent, x: r.left, y: r.top, w: r.width, h: r.height };
        });
    },
  };
  const embedded = document.getElementById("payload-data");
  if (embedded) apply(JSON.parse(embedded.textContent));
  else poll();
  requestAnimationFrame(frame);
})();
