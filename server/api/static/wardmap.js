// wardmap web page: a top-down floor view of the object map, the robots and their paths, a
// nearest-object search and live updates. Plain JS, no library, nothing from the network but
// this server (docs/web.md).
//
// Frames and units: the map frame of the server (x, y on the floor, z up; metres). The view
// maps world (x, y) to CSS pixels: sx = (x - cx) * scale + w / 2, sy = h / 2 - (y - cy) * scale.
//
// Data flow: the update stream (GET /v1/events, read with fetch so it can carry the bearer
// token) is opened first; on its `ready` event the page loads the snapshot (GET /v1/objects,
// pages in parallel) and then applies the updates that arrived meanwhile, in order, so no
// change is missed. Robots and trajectories are polled (GET /v1/robots every ROBOT_POLL_MS).
"use strict";

(() => {
  const PAGE = 1000;            // objects per request (the API's maximum)
  const ROBOT_POLL_MS = 3000;
  const RESULTS = 5;            // search hits shown
  const TOKEN_KEY = "wardmap.token";
  const ABBREV = {
    wheelchair: "W", cart: "Ca", iv_pole: "IV", temperature_gun: "T", cup: "Cu", chair: "Ch",
    bed: "B", door: "D", cabinet: "Cb", wall_monitor: "M", sink: "S", desk: "De", person: "P",
  };
  const PALETTE = ["#e63946", "#457b9d", "#2a9d8f", "#e9c46a", "#f4a261", "#8e7dbe", "#6a994e",
                   "#bc4749", "#1d3557", "#ff7f51", "#4d908e", "#b5838d", "#577590", "#90be6d"];

  // ------------------------------------------------------------------ state (one owner: this closure)
  const state = {
    objects: new Map(),       // object_id -> map object (GET /v1/objects shape), confirmed only
    categories: [],           // names in knowledge-graph order
    robots: [],               // GET /v1/robots
    trajectories: new Map(),  // robot_id -> {keyframes, points: [[x, y], ...]}
    searchPoint: null,        // [x, y] world
    results: [],              // last search hits
    selected: null,           // object_id shown in detail
    loading: true,            // snapshot in flight: updates wait in `pending`
    pending: [],
    live: false,
    firstPaintMs: null,       // performance.now() when the first snapshot was drawn
    timing: { snapshotMs: null, drawMs: null },  // last snapshot's load, last frame's drawing (ms)
    updatesDrawn: new Map(),  // object_id -> Date.now() when its last update was drawn
    meanZ: 1.0,               // mean object centre height: a clicked point's z for searches
    view: { cx: 0, cy: 0, scale: 20, moved: false },  // moved: by the user (no more auto-fit)
    robotsLoaded: false,
  };

  const $ = (id) => document.getElementById(id);
  const canvas = $("map");
  const ctx = canvas.getContext("2d");

  // ------------------------------------------------------------------ auth and requests
  // A token is given once as #token=... and kept for the tab in sessionStorage.
  const hash = new URLSearchParams(location.hash.slice(1));
  if (hash.has("token")) {
    sessionStorage.setItem(TOKEN_KEY, hash.get("token"));
    history.replaceState(null, "", location.pathname + location.search);
  }
  const token = sessionStorage.getItem(TOKEN_KEY);

  class HttpError extends Error {}     // the server answered with an error status
  class NetworkError extends Error {}  // no answer: the server is down or unreachable
  const expected = (err) => err instanceof HttpError || err instanceof NetworkError;

  function banner(text) {
    const b = $("banner");
    b.textContent = text;
    b.hidden = !text;
  }

  async function api(path, options = {}) {
    const headers = Object.assign({ Accept: "application/json" }, options.headers || {});
    if (token) headers.Authorization = "Bearer " + token;
    let resp;
    try {
      resp = await fetch(path, Object.assign({}, options, { headers }));
    } catch (err) {
      throw new NetworkError(path + ": " + err.message);
    }
    if (resp.status === 401 || resp.status === 403) {
      throw new HttpError(`${path}: HTTP ${resp.status}: ` + (token ? "the server refused this page's token; open"
        : "this server needs an access token: open") + ` the page as ${location.pathname}#token=YOUR_TOKEN`);
    }
    if (!resp.ok) throw new HttpError(path + ": HTTP " + resp.status);
    return resp;
  }

  const getJson = async (path) => (await api(path)).json();
  const sleep = (ms) => new Promise((resolve) => setTimeout(resolve, ms));

  // ------------------------------------------------------------------ formatting
  function ago(s) {
    const d = Date.now() / 1000 - s;
    if (d < 0) return "just now";
    if (d < 90) return Math.round(d) + " s ago";
    if (d < 5400) return Math.round(d / 60) + " min ago";
    if (d < 129600) return Math.round(d / 3600) + " h ago";
    return Math.round(d / 86400) + " days ago";
  }
  const when = (s) => new Date(s * 1000).toLocaleString();
  const label = (name) => name.replace(/_/g, " ");
  const robotColour = (id) => {
    const i = state.robots.findIndex((r) => r.robot_id === id);
    return PALETTE[((i < 0 ? 0 : i) * 3 + 1) % PALETTE.length];
  };
  const colourOf = (name) => {
    const i = state.categories.indexOf(name);
    return PALETTE[(i < 0 ? 0 : i) % PALETTE.length];
  };

  // ------------------------------------------------------------------ view
  function size() {
    const r = canvas.getBoundingClientRect();
    return { w: r.width, h: r.height };
  }
  function toScreen(x, y) {
    const { w, h } = size();
    const v = state.view;
    return [(x - v.cx) * v.scale + w / 2, h / 2 - (y - v.cy) * v.scale];
  }
  function toWorld(sx, sy) {
    const { w, h } = size();
    const v = state.view;
    return [(sx - w / 2) / v.scale + v.cx, v.cy - (sy - h / 2) / v.scale];
  }

  function fit() {
    let x0 = Infinity, y0 = Infinity, x1 = -Infinity, y1 = -Infinity;
    const add = (x, y) => { x0 = Math.min(x0, x); y0 = Math.min(y0, y); x1 = Math.max(x1, x); y1 = Math.max(y1, y); };
    for (const o of state.objects.values()) add(o.position[0], o.position[1]);
    for (const t of state.trajectories.values()) for (const p of t.points) add(p[0], p[1]);
    for (const r of state.robots) if (r.map_pose) add(r.map_pose.t[0], r.map_pose.t[1]);
    if (x0 === Infinity) return false;
    const { w, h } = size();
    const v = state.view;
    v.cx = (x0 + x1) / 2;
    v.cy = (y0 + y1) / 2;
    v.scale = Math.max(0.5, Math.min(200, 0.9 * Math.min(w / Math.max(x1 - x0, 1), h / Math.max(y1 - y0, 1))));
    return true;
  }

  function zoom(factor, sx, sy) {
    const { w, h } = size();
    const [wx, wy] = toWorld(sx === undefined ? w / 2 : sx, sy === undefined ? h / 2 : sy);
    const v = state.view;
    v.scale = Math.max(0.5, Math.min(400, v.scale * factor));
    v.moved = true;
    const [nx, ny] = toWorld(sx === undefined ? w / 2 : sx, sy === undefined ? h / 2 : sy);
    v.cx += wx - nx;
    v.cy += wy - ny;
    redraw();
  }

  // ------------------------------------------------------------------ drawing
  let frameRequested = false;
  const drawnCallbacks = [];

  function redraw(then) {
    if (then) drawnCallbacks.push(then);
    if (frameRequested) return;
    frameRequested = true;
    requestAnimationFrame(() => {
      frameRequested = false;
      draw();
      for (const cb of drawnCallbacks.splice(0)) cb();
    });
  }

  function addFootprint(o, w, h) {
    // The box's floor rectangle (size x, y turned by yaw about z) as a closed sub-path, in
    // screen pixels: the corners (+-hx, +-hy) in the box frame, rotated, then scaled.
    const v = state.view;
    const c = Math.cos(o.yaw) * v.scale, s = Math.sin(o.yaw) * v.scale;
    const hx = o.size[0] / 2, hy = o.size[1] / 2;
    const cx = (o.position[0] - v.cx) * v.scale + w / 2, cy = h / 2 - (o.position[1] - v.cy) * v.scale;
    ctx.moveTo(cx - c * hx + s * hy, cy + s * hx + c * hy);
    ctx.lineTo(cx + c * hx + s * hy, cy - s * hx + c * hy);
    ctx.lineTo(cx + c * hx - s * hy, cy - s * hx - c * hy);
    ctx.lineTo(cx - c * hx - s * hy, cy + s * hx - c * hy);
    ctx.closePath();
  }

  function draw() {
    const started = performance.now();
    drawScene();
    state.timing.drawMs = performance.now() - started;
  }

  function drawScene() {
    const dpr = window.devicePixelRatio || 1;
    const { w, h } = size();
    if (canvas.width !== Math.round(w * dpr) || canvas.height !== Math.round(h * dpr)) {
      canvas.width = Math.round(w * dpr);
      canvas.height = Math.round(h * dpr);
    }
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    ctx.clearRect(0, 0, w, h);
    drawGrid(w, h);

    // Trajectories and their keyframes, each robot in its own colour.
    for (const [robot, t] of state.trajectories) {
      const colour = robotColour(robot);
      ctx.strokeStyle = colour;
      ctx.fillStyle = colour;
      ctx.lineWidth = 1.5;
      ctx.globalAlpha = 0.6;
      ctx.beginPath();
      t.points.forEach((p, k) => {
        const [sx, sy] = toScreen(p[0], p[1]);
        if (k === 0) ctx.moveTo(sx, sy); else ctx.lineTo(sx, sy);
      });
      ctx.stroke();
      for (const p of t.points) {
        const [sx, sy] = toScreen(p[0], p[1]);
        ctx.fillRect(sx - 1.5, sy - 1.5, 3, 3);
      }
      ctx.globalAlpha = 1;
    }

    // Objects: their footprints in the category's colour (one path per category: 10,000
    // objects cost a few fills, not 10,000), then icon letters where the box is big enough.
    const hits = new Set(state.results.map((o) => o.object_id));
    const byCategory = new Map();
    for (const o of state.objects.values()) {
      let list = byCategory.get(o.category);
      if (!list) byCategory.set(o.category, (list = []));
      list.push(o);
    }
    ctx.lineWidth = 1;
    for (const [category, list] of byCategory) {
      ctx.beginPath();
      for (const o of list) addFootprint(o, w, h);
      const colour = colourOf(category);
      ctx.globalAlpha = 0.55;
      ctx.fillStyle = colour;
      ctx.fill();
      ctx.globalAlpha = 1;
      ctx.strokeStyle = colour;
      ctx.stroke();
    }
    ctx.textAlign = "center";
    ctx.textBaseline = "middle";
    for (const o of state.objects.values()) {
      const px = Math.max(o.size[0], o.size[1]) * state.view.scale;
      const marked = hits.has(o.object_id) || o.object_id === state.selected;
      if (px < 20 && !marked) continue;
      const [sx, sy] = toScreen(o.position[0], o.position[1]);
      const colour = colourOf(o.category);
      if (px >= 20) {  // the icon: a badge a third of the box, so its footprint stays visible
        const r = Math.min(px / 6, 11);
        ctx.beginPath();
        ctx.arc(sx, sy, r, 0, 2 * Math.PI);
        ctx.fillStyle = "#fff";
        ctx.fill();
        ctx.strokeStyle = colour;
        ctx.stroke();
        ctx.fillStyle = colour;
        ctx.font = `bold ${Math.round(r)}px system-ui, sans-serif`;
        ctx.fillText(ABBREV[o.category] || o.category.slice(0, 2), sx, sy + 0.5);
      }
      if (marked) {
        ctx.beginPath();
        ctx.arc(sx, sy, Math.max(10, px / 2 + 4), 0, 2 * Math.PI);
        ctx.lineWidth = 3;
        ctx.strokeStyle = o.object_id === state.selected ? "#1d3557" : "#e76f51";
        ctx.stroke();
        ctx.lineWidth = 1;
      }
    }

    // Robots: a triangle along the camera's heading; filled when anchored on the map.
    for (const r of state.robots) {
      if (!r.map_pose) continue;
      const [sx, sy] = toScreen(r.map_pose.t[0], r.map_pose.t[1]);
      const [qx, qy, qz, qw] = r.map_pose.q_xyzw;
      // The camera looks along its z axis: the third column of R(q), projected on the floor.
      const heading = Math.atan2(2 * (qy * qz - qw * qx), 2 * (qx * qz + qw * qy));
      ctx.save();
      ctx.translate(sx, sy);
      ctx.rotate(-heading);
      ctx.beginPath();
      ctx.moveTo(12, 0);
      ctx.lineTo(-8, 7);
      ctx.lineTo(-8, -7);
      ctx.closePath();
      ctx.lineWidth = 2;
      ctx.strokeStyle = "#1d2430";
      ctx.fillStyle = r.anchored ? robotColour(r.robot_id) : "#fff";
      ctx.fill();
      ctx.stroke();
      ctx.restore();
      ctx.fillStyle = "#1d2430";
      ctx.font = "12px system-ui, sans-serif";
      ctx.fillText(r.robot_id, sx, sy - 16);
    }

    if (state.searchPoint) {
      const [sx, sy] = toScreen(state.searchPoint[0], state.searchPoint[1]);
      ctx.strokeStyle = "#e63946";
      ctx.lineWidth = 2;
      ctx.beginPath();
      ctx.moveTo(sx - 8, sy); ctx.lineTo(sx + 8, sy);
      ctx.moveTo(sx, sy - 8); ctx.lineTo(sx, sy + 8);
      ctx.stroke();
      ctx.beginPath();
      ctx.arc(sx, sy, 5, 0, 2 * Math.PI);
      ctx.stroke();
    }
  }

  function drawGrid(w, h) {
    // A line every 1, 2, 5, 10, ... metres, at least 40 px apart; the scale bar shows the step.
    const v = state.view;
    let step = 1;
    for (const m of [1, 2, 5, 10, 20, 50, 100, 200, 500]) { step = m; if (m * v.scale >= 40) break; }
    const [x0, y1] = toWorld(0, 0);
    const [x1, y0] = toWorld(w, h);
    ctx.strokeStyle = "#e6e9ee";
    ctx.lineWidth = 1;
    ctx.beginPath();
    for (let x = Math.ceil(x0 / step) * step; x <= x1; x += step) {
      const [sx] = toScreen(x, 0);
      ctx.moveTo(sx, 0); ctx.lineTo(sx, h);
    }
    for (let y = Math.ceil(y0 / step) * step; y <= y1; y += step) {
      const [, sy] = toScreen(0, y);
      ctx.moveTo(0, sy); ctx.lineTo(w, sy);
    }
    ctx.stroke();
    const bar = $("scale");
    bar.style.width = step * v.scale + "px";
    bar.textContent = step + " m";
  }

  // ------------------------------------------------------------------ objects and live updates
  function counts() {
    $("counts").textContent = `${state.objects.size} objects, ${state.robots.length} robots`;
  }

  function applyUpdate(u) {
    const o = u.object;
    if (u.kind === "deleted" || !o.confirmed) state.objects.delete(o.object_id);
    else state.objects.set(o.object_id, o);
    const id = o.object_id;
    redraw(() => state.updatesDrawn.set(id, Date.now()));
  }

  async function loadCategories() {
    const cats = await getJson("/v1/categories");
    state.categories = cats.categories.map((c) => c.name);
    const select = $("category");
    const chosen = select.value;
    select.replaceChildren(...cats.categories.filter((c) => c.mobility !== "moving").map((c) => {
      const opt = document.createElement("option");
      opt.value = c.name;
      opt.textContent = `${label(c.name)} (${c.count})`;
      return opt;
    }));
    if (chosen) select.value = chosen;
    else {  // the first class on the map
      const first = cats.categories.find((c) => c.mobility !== "moving" && c.count > 0);
      if (first) select.value = first.name;
    }
    return cats.total;
  }

  async function loadSnapshot() {
    const started = performance.now();
    state.loading = true;
    const total = await loadCategories();
    const offsets = [];
    for (let k = 0; k === 0 || k < total; k += PAGE) offsets.push(k);
    // format=compact: what the floor view draws (the detail and search read whole objects).
    const pageAt = (k) => getJson(`/v1/objects?format=compact&limit=${PAGE}&offset=${k}`);
    const pages = await Promise.all(offsets.map(pageAt));
    let next = pages[pages.length - 1].next_offset;
    while (next !== null) {  // objects added since the count
      const page = await pageAt(next);
      pages.push(page);
      next = page.next_offset;
    }
    const objects = new Map();
    let zSum = 0;
    for (const page of pages) {
      for (const [id, category, x, y, z, yaw, sx, sy, sz] of page.rows) {
        objects.set(id, { object_id: id, category, position: [x, y, z], yaw, size: [sx, sy, sz] });
        zSum += z;
      }
    }
    state.objects = objects;
    state.timing.snapshotMs = performance.now() - started;
    if (objects.size) state.meanZ = zSum / objects.size;
    state.loading = false;
    for (const u of state.pending.splice(0)) applyUpdate(u);
    // The view fits the map until the user moves it, for the first snapshot and robots.
    if (!state.view.moved && (state.firstPaintMs === null || !state.robotsLoaded)) fit();
    counts();
    redraw(() => {
      if (state.firstPaintMs === null) {
        state.firstPaintMs = performance.now();
        document.body.dataset.ready = "1";
      }
    });
  }

  function onEvent(name, data) {
    if (name === "ready") {
      setLive(true);
      snapshotUntilLoaded();
    } else if (name === "update") {
      const u = JSON.parse(data);
      if (state.loading) state.pending.push(u); else { applyUpdate(u); counts(); }
    }
    // "resync": the server ends the stream next; the loop reconnects and reloads.
  }

  async function snapshotUntilLoaded() {
    // Updates wait in `pending` until a snapshot loads, so a failed one is retried.
    for (let wait = 1000; ; wait = Math.min(2 * wait, 10000)) {
      try {
        await loadSnapshot();
        banner("");
        return;
      } catch (err) {
        if (!expected(err)) throw err;
        banner("Cannot load the map (" + err.message + "); retrying.");
      }
      await sleep(wait);
    }
  }

  function setLive(on) {
    state.live = on;
    const el = $("live");
    el.textContent = on ? "live" : "reconnecting";
    el.className = "live " + (on ? "on" : "off");
  }

  async function streamEvents() {
    // Server-Sent Events over fetch (EventSource cannot send the Authorization header).
    let backoff = 500;
    for (;;) {
      try {
        const resp = await api("/v1/events", { headers: { Accept: "text/event-stream" } });
        const reader = resp.body.pipeThrough(new TextDecoderStream()).getReader();
        let buf = "";
        for (;;) {
          let chunk;
          try {
            chunk = await reader.read();
          } catch (err) {
            throw new NetworkError("/v1/events: " + err.message);
          }
          const { value, done } = chunk;
          if (done) break;
          buf += value;
          if (buf.includes("\r")) {  // CR LF or CR ends a line too; a CR at the end may precede an LF
            const tail = buf.endsWith("\r") ? "\r" : "";
            buf = buf.slice(0, buf.length - tail.length).replace(/\r\n?/g, "\n") + tail;
          }
          let end;
          while ((end = buf.indexOf("\n\n")) >= 0) {
            const block = buf.slice(0, end);
            buf = buf.slice(end + 2);
            let name = "message";
            const data = [];
            for (const line of block.split("\n")) {
              if (line.startsWith(":")) continue;
              const colon = line.indexOf(":");
              const field = colon < 0 ? line : line.slice(0, colon);
              const val = colon < 0 ? "" : line.slice(colon + 1).replace(/^ /, "");
              if (field === "event") name = val;
              else if (field === "data") data.push(val);
            }
            if (name === "ready") backoff = 500;
            onEvent(name, data.join("\n"));
          }
        }
      } catch (err) {
        if (!expected(err)) throw err;
      }
      setLive(false);
      await sleep(backoff);
      backoff = Math.min(2 * backoff, 10000);
    }
  }

  // ------------------------------------------------------------------ robots
  async function pollRobots() {
    const body = await getJson("/v1/robots");
    state.robots = body.robots;
    for (const r of state.robots) {
      const t = state.trajectories.get(r.robot_id);
      if (!t || t.keyframes !== r.keyframes) {
        const traj = await getJson(`/v1/robots/${encodeURIComponent(r.robot_id)}/trajectory?frame=map`);
        state.trajectories.set(r.robot_id, { keyframes: r.keyframes, points: traj.poses.map((p) => p.t) });
      }
    }
    const list = $("robots");
    list.replaceChildren(...state.robots.map((r) => {
      const li = document.createElement("li");
      const where = r.map_pose ? ` at (${r.map_pose.t[0].toFixed(1)}, ${r.map_pose.t[1].toFixed(1)}) m` : "";
      li.innerHTML = `<b></b> <span class="${r.anchored ? "anchored" : "floating"}"></span><br><span class="sub"></span>`;
      li.children[0].textContent = r.robot_id;
      li.children[1].textContent = r.anchored ? "anchored" : "not anchored";
      li.children[3].textContent = `${r.keyframes} keyframes${where}, last ${ago(r.last_seen_s)}`;
      return li;
    }));
    const origin = $("origin");
    const chosen = origin.value;
    origin.replaceChildren(origin.options[0], ...state.robots.filter((r) => r.map_pose).map((r) => {
      const opt = document.createElement("option");
      opt.value = "robot:" + r.robot_id;
      opt.textContent = `robot ${r.robot_id}'s position`;
      return opt;
    }));
    origin.value = [...origin.options].some((o) => o.value === chosen) ? chosen : "point";
    if (!state.view.moved && (!state.robotsLoaded || state.firstPaintMs === null)) fit();
    state.robotsLoaded = true;
    counts();
    redraw();
  }

  async function robotsLoop() {
    for (;;) {
      try {
        await pollRobots();
      } catch (err) {
        if (!expected(err)) throw err;
        banner(err.message);
      }
      await sleep(ROBOT_POLL_MS);
    }
  }

  // ------------------------------------------------------------------ search
  function searchOrigin() {
    const origin = $("origin").value;
    if (origin.startsWith("robot:")) {
      const r = state.robots.find((x) => x.robot_id === origin.slice(6));
      return r && r.map_pose ? r.map_pose.t : null;
    }
    // A clicked point has no height: search at the mean object height, so the 3D centre
    // distance is close to the distance on the floor.
    return state.searchPoint ? [state.searchPoint[0], state.searchPoint[1], state.meanZ] : null;
  }

  async function search(event) {
    event.preventDefault();
    const p = searchOrigin();
    const list = $("results");
    if (!p) {
      list.replaceChildren(Object.assign(document.createElement("li"), { textContent: "Click the map first." }));
      return;
    }
    const cat = $("category").value;
    const near = p.map((v) => v.toFixed(3)).join(",");
    const body = await getJson(`/v1/objects?category=${encodeURIComponent(cat)}&near=${near}&limit=${RESULTS}`);
    state.results = body.objects;
    list.replaceChildren(...body.objects.map((o) => {
      const li = document.createElement("li");
      li.dataset.objectId = o.object_id;
      li.innerHTML = "<b></b> <span></span><br><span class=sub></span>";
      li.children[0].textContent = `${label(o.category)} #${o.object_id}`;
      li.children[1].textContent = `${o.distance_m.toFixed(1)} m`;
      li.children[3].textContent = `last seen ${ago(o.last_seen_s)} (${when(o.last_seen_s)})`;
      li.addEventListener("click", () => showDetail(o.object_id).catch(failed));
      return li;
    }));
    if (!body.objects.length) list.replaceChildren(Object.assign(document.createElement("li"), { textContent: `No ${label(cat)} on the map.` }));
    redraw();
  }

  // ------------------------------------------------------------------ detail
  async function showDetail(id) {
    state.selected = id;
    for (const li of $("results").children) li.classList.toggle("selected", li.dataset.objectId === String(id));
    redraw();
    const d = await getJson(`/v1/objects/${id}?observations=20`);
    const o = d.object;
    $("detail-title").textContent = `${label(o.category)} #${o.object_id}`;
    const rows = [
      ["category", label(o.category)],
      ["confidence", o.confidence.toFixed(2)],
      ["size", o.size.map((v) => v.toFixed(2)).join(" × ") + " m"],
      ["position", o.position.map((v) => v.toFixed(2)).join(", ") + " m"],
      ["colour", o.color_rgb ? "rgb(" + o.color_rgb.map(Math.round).join(", ") + ")" : "unknown"],
      ["first seen", when(o.first_seen_s)],
      ["last seen", `${ago(o.last_seen_s)} (${when(o.last_seen_s)})`],
      ["observations", String(o.n_observations)],
      ["seen by", o.robots.length ? o.robots.join(", ") : "no robot"],
    ];
    const dl = $("detail-fields");
    dl.replaceChildren(...rows.flatMap(([k, v]) => {
      const dt = document.createElement("dt");
      const dd = document.createElement("dd");
      dt.textContent = k;
      dd.textContent = v;
      dd.dataset.field = k;
      if (k === "colour" && o.color_rgb) {
        const sw = document.createElement("span");
        sw.className = "swatch";
        sw.style.background = dd.textContent;
        dd.prepend(sw, " ");
      }
      return [dt, dd];
    }));
    $("detail").hidden = false;
    await showThumbnail(d);
  }

  async function showThumbnail(d) {
    const fig = $("detail-figure");
    const stored = new Set(d.keyframes.filter((k) => k.stored).map((k) => `${k.robot_id}/${k.session_id}/${k.seq}`));
    const ob = d.observations.find((x) => stored.has(`${x.robot_id}/${x.session_id}/${x.seq}`));
    if (!ob) { fig.hidden = true; return; }
    const path = ["/v1/keyframes", ob.robot_id, ob.session_id, ob.seq, "image"].map(encodeURIComponent).join("/").replace(/%2F/g, "/");
    const blob = await (await api(path, { headers: { Accept: "image/jpeg" } })).blob();
    const img = await createImageBitmap(blob);
    const c = $("thumb");
    c.width = 320;
    c.height = Math.round(320 * img.height / img.width);
    const g = c.getContext("2d");
    const k = c.width / img.width;
    g.drawImage(img, 0, 0, c.width, c.height);
    const [x1, y1, x2, y2] = ob.box_xyxy;
    g.strokeStyle = "#ffd60a";
    g.lineWidth = 2;
    g.strokeRect(x1 * k, y1 * k, (x2 - x1) * k, (y2 - y1) * k);
    $("thumb-caption").textContent = `robot ${ob.robot_id}, keyframe ${ob.session_id}/${ob.seq}, ${when(ob.stamp)}`;
    fig.hidden = false;
  }

  // ------------------------------------------------------------------ input
  function objectAt(sx, sy) {
    // The smallest footprint (grown by 4 px) holding the point.
    const [wx, wy] = toWorld(sx, sy);
    const pad = 4 / state.view.scale;
    let best = null, bestArea = Infinity;
    for (const o of state.objects.values()) {
      const c = Math.cos(o.yaw), s = Math.sin(o.yaw);
      const dx = wx - o.position[0], dy = wy - o.position[1];
      const u = c * dx + s * dy, v = -s * dx + c * dy;  // in the box's frame
      if (Math.abs(u) <= o.size[0] / 2 + pad && Math.abs(v) <= o.size[1] / 2 + pad) {
        const area = o.size[0] * o.size[1];
        if (area < bestArea) { best = o; bestArea = area; }
      }
    }
    return best;
  }

  const pointers = new Map();
  let drag = null;
  canvas.addEventListener("pointerdown", (e) => {
    canvas.setPointerCapture(e.pointerId);
    pointers.set(e.pointerId, [e.offsetX, e.offsetY]);
    drag = { x: e.offsetX, y: e.offsetY, moved: false, pinch: pointers.size > 1 ? pinchDistance() : 0 };
  });
  canvas.addEventListener("pointermove", (e) => {
    if (!pointers.has(e.pointerId) || !drag) return;
    pointers.set(e.pointerId, [e.offsetX, e.offsetY]);
    if (pointers.size > 1) {  // two fingers: pinch to zoom
      const d = pinchDistance();
      if (drag.pinch > 0) zoom(d / drag.pinch);
      drag.pinch = d;
      drag.moved = true;
      return;
    }
    const dx = e.offsetX - drag.x, dy = e.offsetY - drag.y;
    if (!drag.moved && Math.hypot(dx, dy) < 5) return;
    drag.moved = true;
    state.view.moved = true;
    state.view.cx -= dx / state.view.scale;
    state.view.cy += dy / state.view.scale;
    drag.x = e.offsetX;
    drag.y = e.offsetY;
    redraw();
  });
  canvas.addEventListener("pointerup", (e) => {
    pointers.delete(e.pointerId);
    if (!drag || drag.moved) { if (!pointers.size) drag = null; return; }
    drag = null;
    const o = objectAt(e.offsetX, e.offsetY);
    if (o) {
      showDetail(o.object_id).catch(failed);
    } else {
      state.searchPoint = toWorld(e.offsetX, e.offsetY);
      $("origin").value = "point";
      $("origin-point").textContent =
        `Point (${state.searchPoint[0].toFixed(2)}, ${state.searchPoint[1].toFixed(2)}) m`;
      redraw();
    }
  });
  canvas.addEventListener("pointercancel", (e) => { pointers.delete(e.pointerId); drag = null; });
  function pinchDistance() {
    const [a, b] = [...pointers.values()];
    return Math.hypot(a[0] - b[0], a[1] - b[1]);
  }
  canvas.addEventListener("wheel", (e) => {
    e.preventDefault();
    zoom(Math.exp(-e.deltaY / 500), e.offsetX, e.offsetY);
  }, { passive: false });
  $("zoom-in").addEventListener("click", () => zoom(1.5));
  $("zoom-out").addEventListener("click", () => zoom(1 / 1.5));
  $("zoom-fit").addEventListener("click", () => { fit(); state.view.moved = false; redraw(); });
  $("search-form").addEventListener("submit", (e) => search(e).catch(failed));
  $("detail-close").addEventListener("click", () => { $("detail").hidden = true; state.selected = null; redraw(); });
  window.addEventListener("resize", () => redraw());

  function failed(err) {
    if (expected(err)) { banner(err.message); return; }
    throw err;
  }

  // For tests and benchmarks: read-only views of the state and the view transform.
  window.wardmap = { state, toScreen, toWorld, colourOf };

  setLive(false);
  streamEvents();
  robotsLoop();
  redraw();
})();
