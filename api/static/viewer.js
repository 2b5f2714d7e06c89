/*
 * veinmosaic browser viewer: the Deep Zoom mosaic of one session, live while the scan goes on.
 *
 * - The session id is the last part of the page path; a view-only token (?token=) is passed on to every
 *   API call (fetch, tile URLs, the EventSource), since a browser cannot add an Authorization header there.
 *   It is kept in memory only: history.replaceState takes it out of the address bar as soon as it is read.
 * - Tiles come from a custom OpenSeadragon tile source built from mosaic.json "dzi"; each tile URL carries
 *   the results version (v) and the tile's revision (rev), so the browser may cache tiles for ever and a
 *   changed tile simply has a new URL.
 * - Server-Sent Events (/events) bring progress: new tile revisions, the tail of the probe path, counters.
 *   Changed tiles are reloaded by double buffering: a new TiledImage with the new revisions is loaded
 *   invisibly on top of the old one (unchanged tiles come from cache) and swapped in when fully loaded.
 * - The probe path is an SVG overlay in DZI pixels: px = dzi.origin_px + mm * px_per_mm, with start and end
 *   markers and crosses where lost/rejected frames probably were; hovering shows a frame's seq, time, load, status.
 * - A mm scale bar follows the zoom; the Measure tool reads the distance of two clicked points in mm.
 * - The coverage layer is the whole coverage image placed on the Deep Zoom canvas (vein and force are tiled).
 * - A banner shows the session's warnings (GET /v1/sessions/{id}: >5 % frames lost, failed, reprocess running).
 * Exposes window.veinmosaicViewer = {viewer, revisions, state, ...} for tests and debugging.
 */
(function () {
  "use strict";

  const SVG_NS = "http://www.w3.org/2000/svg";
  const SWAP_TIMEOUT_MS = 5000; // swap even if some tile never finishes loading
  const PATH_REFRESH_MS = 2000; // at most one full path re-read per this interval
  const SESSION_POLL_MS = 5000; // frames received / status while live

  const parts = window.location.pathname.split("/").filter(Boolean);
  const sessionId = decodeURIComponent(parts[parts.length - 1] || "");
  // The view-only token is read once, kept in this closure for every API call, and taken out of the address
  // bar (so it stays in no history entry, bookmark or screenshot of the URL); a reload needs the link again.
  const query = new URLSearchParams(window.location.search);
  const token = query.get("token") || "";
  if (query.has("token")) {
    query.delete("token");
    const rest = query.toString();
    const bare = window.location.pathname + (rest ? "?" + rest : "") + window.location.hash;
    window.history.replaceState(window.history.state, "", bare);
  }
  const base = "/v1/sessions/" + encodeURIComponent(sessionId);

  const revisions = { vein: {}, force: {} };
  const state = {
    session: sessionId,
    status: "connecting",
    layer: "vein",
    resultsVersion: null,
    mosaicVersion: 0,
    dzi: null,
    pxPerMm: null,
    extentMm: null,
    frames: { processed: 0, ok: 0, lost: 0, rejected: 0, no_contact: 0, in_fragments: 0, keyframes: 0, tracked: 0 },
    lag: null, // while live: {p50_s, p95_s, frames} from GET /v1/sessions/{id}
    framesKnown: false, // counters arrived (until then the status line says "loading results")
    received: null,
    path: new Map(), // seq -> [x_mm, y_mm, status]
    rows: new Map(), // seq -> full path row (t_s, fz_n, reason, ...) from /path
    mosaic: null, // mosaic.json geometry of the whole images (origin_px, width, height)
    warnings: [], // [{code, message}] from GET /v1/sessions/{id}: the banner
    scaleText: "",
    measure: { active: false, points: [], mm: null },
    fitted: false,
    userMoved: false,
    done: false,
    events: 0,
    swaps: 0,
    loading: false,
    error: null,
  };

  function apiUrl(path, params) {
    const q = new URLSearchParams();
    Object.entries(params || {}).forEach(([k, v]) => {
      if (v !== null && v !== undefined) q.set(k, String(v));
    });
    if (token) q.set("token", token);
    const s = q.toString();
    return base + path + (s ? "?" + s : "");
  }

  async function getJson(path, params) {
    const resp = await fetch(apiUrl(path, params), { cache: "no-cache", credentials: "omit" });
    if (resp.status === 404) return null;
    if (!resp.ok) {
      let message = "HTTP " + resp.status;
      try {
        message = (await resp.json()).error.message || message;
      } catch (e) { /* not JSON */ }
      const err = new Error(message);
      err.status = resp.status;
      throw err;
    }
    return resp.json();
  }

  // ----- OpenSeadragon ---------------------------------------------------------------------------------------
  const viewer = OpenSeadragon({
    id: "viewer",
    prefixUrl: "/static/vendor/openseadragon/images/",
    drawer: "canvas", // headless browsers and many VMs have no WebGL
    showNavigator: false,
    showRotationControl: false,
    showFullPageControl: false,
    visibilityRatio: 0.1,
    constrainDuringPan: false,
    maxZoomPixelRatio: 6,
    minZoomImageRatio: 0.5,
    animationTime: 0.5,
    immediateRender: false,
    preserveImageSizeOnResize: true,
    gestureSettingsMouse: { clickToZoom: false, dblClickToZoom: true },
  });

  let current = null; // the TiledImage on screen
  let pending = null; // the TiledImage being loaded (invisible) to replace it
  let dirty = false; // revisions changed while `pending` was loading

  function makeTileSource(layer, dzi, version) {
    return {
      width: dzi.width,
      height: dzi.height,
      tileSize: dzi.tile_size,
      tileOverlap: 0,
      minLevel: 0,
      maxLevel: dzi.max_level,
      getTileUrl: function (level, x, y) {
        const key = level + "/" + x + "_" + y;
        const rev = (revisions[layer] && revisions[layer][key]) || 0;
        return apiUrl("/mosaic_files/" + level + "/" + x + "_" + y + ".png", { layer: layer, v: version, rev: rev });
      },
    };
  }

  // The coverage layer is one whole image (mosaic.png?layer=coverage), placed where the mosaic lies on the
  // Deep Zoom canvas; vein and force are tiled.
  function layerPlacement() {
    const d = state.dzi;
    if (state.layer !== "coverage") return { source: makeTileSource(state.layer, d, state.resultsVersion), x: 0, y: 0, width: 1 };
    const m = state.mosaic;
    if (!m || !m.width || !m.origin_px) return null;
    const url = apiUrl("/mosaic.png", { layer: "coverage", v: state.resultsVersion, mv: state.mosaicVersion });
    return {
      source: { type: "image", url: url, buildPyramid: false, crossOriginPolicy: false },
      x: (d.origin_px[0] - m.origin_px[0]) / d.width,
      y: (d.origin_px[1] - m.origin_px[1]) / d.width,
      width: m.width / d.width,
    };
  }

  function refreshTiles() {
    if (!state.dzi) return;
    if (pending) {
      dirty = true;
      return;
    }
    dirty = false;
    const first = current === null;
    state.loading = true;
    const placement = layerPlacement();
    if (!placement) {
      state.loading = false;
      return;
    }
    viewer.addTiledImage({
      tileSource: placement.source,
      x: placement.x,
      y: placement.y,
      width: placement.width,
      opacity: first ? 1 : 0,
      preload: true,
      success: function (event) {
        const item = event.item;
        pending = item;
        let finished = false;
        const finish = function () {
          if (finished) return;
          finished = true;
          const old = current;
          item.setOpacity(1);
          current = item;
          pending = null;
          if (old) viewer.world.removeItem(old);
          state.swaps += 1;
          state.loading = false;
          if (first) fitToExtent(true);
          if (dirty) refreshTiles();
        };
        if (item.getFullyLoaded()) {
          finish();
        } else {
          item.addHandler("fully-loaded-change", function (e) {
            if (e.fullyLoaded) finish();
          });
          window.setTimeout(finish, SWAP_TIMEOUT_MS);
        }
      },
      error: function (event) {
        pending = null;
        state.loading = false;
        state.error = "tiles: " + (event.message || "failed");
        render();
      },
    });
  }

  // ----- probe path overlay --------------------------------------------------------------------------------
  const svg = document.createElementNS(SVG_NS, "svg");
  svg.setAttribute("id", "path-overlay");
  const group = document.createElementNS(SVG_NS, "g");
  const strokeLines = document.createElementNS(SVG_NS, "g"); // one polyline per stroke: never joined through the air
  strokeLines.setAttribute("id", "path-strokes");
  const marker = document.createElementNS(SVG_NS, "circle"); // the latest frame, while live
  marker.setAttribute("r", "5");
  marker.setAttribute("class", "now");
  marker.setAttribute("visibility", "hidden");
  const startMark = document.createElementNS(SVG_NS, "circle");
  startMark.setAttribute("r", "7");
  startMark.setAttribute("class", "start");
  const endMark = document.createElementNS(SVG_NS, "rect");
  endMark.setAttribute("width", "12");
  endMark.setAttribute("height", "12");
  endMark.setAttribute("class", "end");
  const lostGroup = document.createElementNS(SVG_NS, "g");
  const measureGroup = document.createElementNS(SVG_NS, "g");
  measureGroup.setAttribute("class", "measure");
  group.appendChild(strokeLines);
  svg.appendChild(group);
  svg.appendChild(lostGroup);
  svg.appendChild(startMark);
  svg.appendChild(endMark);
  svg.appendChild(marker);
  svg.appendChild(measureGroup);
  viewer.element.appendChild(svg);
  let lastPoint = null;
  let firstPoint = null;
  let lostPoints = []; // [[dzi x, dzi y, seq]] where a lost/rejected frame probably was

  function dziPoint(x_mm, y_mm) {
    const d = state.dzi;
    return [d.origin_px[0] + x_mm * state.pxPerMm, d.origin_px[1] + y_mm * state.pxPerMm];
  }

  function placed(entry) {
    return entry && entry[2] === "ok" && entry[0] !== null && entry[1] !== null && isFinite(entry[0]) && isFinite(entry[1]);
  }

  function inTheAir(entry) {
    return entry && entry[4] === "no_contact"; // taken off the skin between strokes: not a lost frame
  }

  function drawPath() {
    if (!state.dzi || !state.pxPerMm) return;
    const seqs = Array.from(state.path.keys()).sort((a, b) => a - b);
    const strokes = new Map(); // stroke number (or "" when unknown) -> ["x,y", ...]
    const okSeqs = [];
    lastPoint = null;
    firstPoint = null;
    for (const seq of seqs) {
      const entry = state.path.get(seq);
      if (!placed(entry)) continue;
      const p = dziPoint(entry[0], entry[1]);
      const key = entry[3] === null || entry[3] === undefined ? "" : String(entry[3]);
      if (!strokes.has(key)) strokes.set(key, []);
      strokes.get(key).push(p[0].toFixed(1) + "," + p[1].toFixed(1));
      okSeqs.push(seq);
      if (!firstPoint) firstPoint = p;
      lastPoint = p;
    }
    while (strokeLines.firstChild) strokeLines.removeChild(strokeLines.firstChild);
    for (const [key, pts] of strokes) {
      const line = document.createElementNS(SVG_NS, "polyline");
      line.setAttribute("points", pts.join(" "));
      line.setAttribute("data-stroke", key);
      strokeLines.appendChild(line);
    }
    // a frame not placed is marked between its placed neighbours (by seq): where the probe most likely was
    lostPoints = [];
    for (const seq of seqs) {
      const entry = state.path.get(seq);
      if (placed(entry) || inTheAir(entry)) continue;
      let lo = null;
      let hi = null;
      for (const s of okSeqs) {
        if (s < seq) lo = s;
        else if (hi === null) hi = s;
      }
      const a = lo !== null ? state.path.get(lo) : null;
      const b = hi !== null ? state.path.get(hi) : null;
      let xy = null;
      if (a && b) {
        const f = (seq - lo) / (hi - lo);
        xy = [a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1])];
      } else if (a || b) {
        xy = [(a || b)[0], (a || b)[1]];
      }
      if (xy) lostPoints.push(dziPoint(xy[0], xy[1]).concat([seq]));
    }
    placeOverlay();
  }

  function elementScale() {
    const W = state.dzi.width;
    const vp = viewer.viewport;
    const p0 = vp.pixelFromPoint(new OpenSeadragon.Point(0, 0), true);
    const p1 = vp.pixelFromPoint(new OpenSeadragon.Point(1, 0), true);
    return { p0: p0, s: (p1.x - p0.x) / W }; // element px per DZI px
  }

  function toElement(p, t) {
    return [t.p0.x + p[0] * t.s, t.p0.y + p[1] * t.s];
  }

  function placeOverlay() {
    if (!state.dzi) return;
    const t = elementScale();
    group.setAttribute("transform", "translate(" + t.p0.x + "," + t.p0.y + ") scale(" + t.s + ")");
    const show = function (el, p, dx, dy, xAttr, yAttr) {
      if (!p) {
        el.setAttribute("visibility", "hidden");
        return;
      }
      const e = toElement(p, t);
      el.setAttribute(xAttr, String(e[0] + dx));
      el.setAttribute(yAttr, String(e[1] + dy));
      el.setAttribute("visibility", "visible");
    };
    show(marker, state.done ? null : lastPoint, 0, 0, "cx", "cy");
    show(startMark, firstPoint, 0, 0, "cx", "cy");
    show(endMark, state.done || state.status === "done" ? lastPoint : null, -6, -6, "x", "y");
    while (lostGroup.firstChild) lostGroup.removeChild(lostGroup.firstChild);
    for (const p of lostPoints) {
      const e = toElement(p, t);
      const cross = document.createElementNS(SVG_NS, "path");
      const entry = state.path.get(p[2]);
      // every not-placed frame is a "lost" cross; a rejected one is also classed "rejected" (its own colour)
      cross.setAttribute("class", entry && entry[2] === "rejected" ? "lost rejected" : "lost");
      cross.setAttribute("d", "M" + (e[0] - 5) + "," + (e[1] - 5) + "l10,10m0,-10l-10,10");
      lostGroup.appendChild(cross);
    }
    drawMeasure(t);
    drawScaleBar(t);
  }

  // ----- scale bar: a round number of mm, 60-160 px long ------------------------------------------------------
  const scaleBar = document.getElementById("scale-bar");
  const scaleLine = scaleBar.querySelector(".bar");
  const scaleLabel = scaleBar.querySelector(".label");

  function drawScaleBar(t) {
    if (!state.pxPerMm) {
      scaleBar.hidden = true;
      return;
    }
    const pxPerMm = t.s * state.pxPerMm; // screen px per mm
    const target = 120 / pxPerMm;
    const pow = Math.pow(10, Math.floor(Math.log10(target)));
    let mm = pow;
    for (const k of [1, 2, 5, 10]) {
      if (k * pow * pxPerMm <= 160) mm = k * pow;
    }
    scaleLine.style.width = (mm * pxPerMm).toFixed(1) + "px";
    state.scaleText = (mm >= 1 ? String(Math.round(mm)) : mm.toPrecision(1)) + " mm";
    state.scaleBarPx = mm * pxPerMm;
    state.scaleBarMm = mm;
    scaleLabel.textContent = state.scaleText;
    scaleBar.hidden = false;
  }

  // ----- measuring tool: two clicks, the distance in mm -----------------------------------------------------
  const measureButton = document.getElementById("measure");

  function drawMeasure(t) {
    while (measureGroup.firstChild) measureGroup.removeChild(measureGroup.firstChild);
    const pts = state.measure.points.map((p) => toElement(p, t));
    if (pts.length === 2) {
      const l = document.createElementNS(SVG_NS, "line");
      l.setAttribute("x1", pts[0][0]);
      l.setAttribute("y1", pts[0][1]);
      l.setAttribute("x2", pts[1][0]);
      l.setAttribute("y2", pts[1][1]);
      measureGroup.appendChild(l);
      const label = document.createElementNS(SVG_NS, "text");
      label.setAttribute("x", String((pts[0][0] + pts[1][0]) / 2 + 8));
      label.setAttribute("y", String((pts[0][1] + pts[1][1]) / 2 - 8));
      label.setAttribute("id", "measure-label");
      label.textContent = state.measure.mm.toFixed(1) + " mm";
      measureGroup.appendChild(label);
    }
    for (const p of pts) {
      const c = document.createElementNS(SVG_NS, "circle");
      c.setAttribute("cx", p[0]);
      c.setAttribute("cy", p[1]);
      c.setAttribute("r", "4");
      measureGroup.appendChild(c);
    }
  }

  function setMeasuring(on) {
    state.measure.active = on;
    measureButton.setAttribute("aria-pressed", on ? "true" : "false");
    if (on) {
      state.measure.points = [];
      state.measure.mm = null;
    }
    if (state.dzi) placeOverlay();
    render();
  }

  measureButton.addEventListener("click", function () {
    setMeasuring(!state.measure.active);
  });

  viewer.addHandler("canvas-click", function (event) {
    if (!state.measure.active || !event.quick || !state.dzi || !state.pxPerMm) return;
    event.preventDefaultAction = true;
    const vpPoint = viewer.viewport.pointFromPixel(event.position, true);
    const p = [vpPoint.x * state.dzi.width, vpPoint.y * state.dzi.width]; // DZI px
    if (state.measure.points.length >= 2) state.measure.points = [];
    state.measure.points.push(p);
    if (state.measure.points.length === 2) {
      const [a, b] = state.measure.points;
      state.measure.mm = Math.hypot(b[0] - a[0], b[1] - a[1]) / state.pxPerMm;
    } else {
      state.measure.mm = null;
    }
    placeOverlay();
    render();
  });

  // ----- hovering the path: the nearest frame within 12 px --------------------------------------------------
  const tooltip = document.getElementById("tooltip");

  function frameText(seq) {
    const row = state.rows.get(seq);
    const entry = state.path.get(seq);
    const status = row ? row.status : entry ? entry[2] : "?";
    let text = "frame " + seq;
    if (row && row.t_s !== null && row.t_s !== undefined) text += " · t " + Number(row.t_s).toFixed(2) + " s";
    if (row && row.fz_n !== null && row.fz_n !== undefined) text += " · load " + Number(row.fz_n).toFixed(1) + " N";
    text += " · " + status;
    if (row && row.reason) text += " (" + row.reason.replace(/_/g, " ") + ")";
    return text;
  }

  function nearestFrame(x, y) {
    if (!state.dzi || !state.pxPerMm) return null;
    const t = elementScale();
    let best = null;
    let bestD = 12;
    const consider = function (p, seq) {
      const e = toElement(p, t);
      const d = Math.hypot(e[0] - x, e[1] - y);
      if (d <= bestD) {
        bestD = d;
        best = { seq: seq, x: e[0], y: e[1] };
      }
    };
    for (const [seq, entry] of state.path) {
      if (placed(entry)) consider(dziPoint(entry[0], entry[1]), seq);
    }
    for (const p of lostPoints) consider(p, p[2]);
    return best;
  }

  viewer.element.addEventListener("pointermove", function (e) {
    const box = viewer.element.getBoundingClientRect();
    const hit = svg.classList.contains("hidden") ? null : nearestFrame(e.clientX - box.left, e.clientY - box.top);
    state.hover = hit ? hit.seq : null;
    if (!hit) {
      tooltip.hidden = true;
      return;
    }
    tooltip.textContent = frameText(hit.seq);
    tooltip.hidden = false;
    const left = Math.min(e.clientX + 14, window.innerWidth - tooltip.offsetWidth - 4); // stays on screen
    tooltip.style.left = Math.max(4, left) + "px";
    tooltip.style.top = e.clientY + 14 + "px";
  });
  viewer.element.addEventListener("pointerleave", function () {
    tooltip.hidden = true;
  });

  viewer.addHandler("update-viewport", placeOverlay);
  viewer.addHandler("resize", placeOverlay);
  ["canvas-drag", "canvas-scroll", "canvas-pinch", "canvas-double-click"].forEach(function (name) {
    viewer.addHandler(name, function () {
      state.userMoved = true;
    });
  });

  function fitToExtent(immediately) {
    const e = state.extentMm;
    if (!e || !state.dzi || !state.pxPerMm) return;
    const W = state.dzi.width;
    const a = dziPoint(e[0], e[1]);
    const b = dziPoint(e[2], e[3]);
    const w = (b[0] - a[0]) / W;
    const h = (b[1] - a[1]) / W;
    const pad = 0.06 * Math.max(w, h, 1e-6);
    viewer.viewport.fitBounds(new OpenSeadragon.Rect(a[0] / W - pad, a[1] / W - pad, w + 2 * pad, h + 2 * pad), immediately);
    state.fitted = true;
  }

  // ----- state updates ---------------------------------------------------------------------------------------
  function applyMosaic(doc) {
    if (!doc || !doc.dzi) return false;
    const newVersion = doc.results_version !== undefined ? doc.results_version : state.resultsVersion;
    const versionChanged = state.resultsVersion !== null && newVersion !== state.resultsVersion;
    state.resultsVersion = newVersion;
    state.mosaicVersion = doc.version || 0;
    state.dzi = doc.dzi;
    state.pxPerMm = doc.px_per_mm;
    for (const layer of ["vein", "force"]) {
      revisions[layer] = Object.assign({}, (doc.revisions && doc.revisions[layer]) || {});
    }
    if (doc.extent_mm !== undefined) state.extentMm = doc.extent_mm;
    if (doc.width && doc.origin_px) state.mosaic = { width: doc.width, height: doc.height, origin_px: doc.origin_px };
    if (doc.frames) {
      Object.assign(state.frames, doc.frames);
      state.framesKnown = true;
    }
    if (doc.status) state.status = doc.status;
    if (versionChanged) state.path = new Map();
    return true;
  }

  function mergePath(rows) {
    for (const row of rows || []) {
      state.path.set(row[0], [row[1], row[2], row[3], row[4], row[5]]); // x, y, status, stroke, reason
    }
  }

  function autoFit() {
    if (state.extentMm && !state.userMoved) fitToExtent(!state.fitted);
  }

  function applySnapshot(doc) {
    state.status = doc.status || state.status;
    if (doc.frames_received !== undefined) state.received = doc.frames_received;
    if (doc.mosaic) applyMosaic(doc.mosaic);
    state.path = new Map();
    mergePath(doc.path);
    drawPath();
    refreshTiles();
    autoFit();
    render();
    schedulePathReload(); // the full rows (time, load, reason) for hovering
  }

  async function reloadMosaic() {
    const doc = await getJson("/mosaic.json");
    if (doc && applyMosaic(doc)) {
      refreshTiles();
      await reloadPath();
      autoFit();
      render();
    }
  }

  let pathTimer = null;
  let lastPathLoad = 0;
  async function reloadPath() {
    lastPathLoad = Date.now();
    const rows = await getJson("/path", state.resultsVersion ? { v: state.resultsVersion } : {});
    if (!rows) return;
    state.path = new Map(rows.map((r) => [r.seq, [r.x_mm, r.y_mm, r.status, r.stroke, r.reason]]));
    state.rows = new Map(rows.map((r) => [r.seq, r]));
    drawPath();
  }

  function schedulePathReload() {
    if (pathTimer) return;
    const wait = Math.max(0, PATH_REFRESH_MS - (Date.now() - lastPathLoad));
    pathTimer = window.setTimeout(function () {
      pathTimer = null;
      reloadPath().catch(showError);
    }, wait);
  }

  function applyProgress(data) {
    state.events += 1;
    if (!state.dzi || (data.version !== undefined && data.version !== state.resultsVersion)) {
      reloadMosaic().catch(showError); // first data, or a new results version (reprocess)
      return;
    }
    let changed = false;
    for (const layer of ["vein", "force"]) {
      const tiles = (data.tiles && data.tiles[layer]) || {};
      for (const key of Object.keys(tiles)) {
        if (revisions[layer][key] !== tiles[key]) {
          revisions[layer][key] = tiles[key];
          changed = true;
        }
      }
    }
    if (data.mosaic_version !== undefined) state.mosaicVersion = data.mosaic_version;
    for (const k of ["processed", "ok", "lost", "rejected", "no_contact", "in_fragments", "keyframes", "tracked"]) {
      if (data[k] !== undefined) {
        state.frames[k] = data[k];
        state.framesKnown = true;
      }
    }
    if (state.layer === "coverage" && data.mosaic_version !== undefined) changed = true;
    if (data.extent_mm !== undefined && data.extent_mm !== null) state.extentMm = data.extent_mm;
    if (data.status) state.status = data.status;
    mergePath(data.path_tail);
    drawPath();
    if (data.path_reset) schedulePathReload();
    if (changed) refreshTiles();
    if (data.status === "done" || data.path_reset) schedulePathReload();
    autoFit();
    render();
  }

  // ----- events --------------------------------------------------------------------------------------------
  let source = null;
  function connect() {
    source = new EventSource(apiUrl("/events"));
    source.addEventListener("snapshot", function (e) {
      state.error = null;
      applySnapshot(JSON.parse(e.data));
    });
    source.addEventListener("progress", function (e) {
      applyProgress(JSON.parse(e.data));
    });
    source.addEventListener("version", function () {
      reloadMosaic().catch(showError); // a reprocess made a new results version current
    });
    source.addEventListener("done", function (e) {
      const data = JSON.parse(e.data);
      source.close();
      state.done = true;
      state.status = data.status || "done";
      reloadMosaic()
        .then(pollSession)
        .catch(showError);
      render();
    });
    source.onopen = function () {
      state.error = null;
      render();
    };
    source.onerror = function () {
      if (state.done) return;
      if (source.readyState === EventSource.CLOSED) {
        // the server refused (expired link, no such session): say so instead of retrying for ever
        state.error = "disconnected: the link may have expired";
      } else {
        state.error = "reconnecting…";
      }
      render();
    };
  }

  async function pollSession() {
    try {
      const s = await getJson("");
      if (s) {
        state.received = s.frames_received;
        if (s.status) state.status = s.status;
        state.warnings = s.warnings || [];
        state.lag = s.status !== "done" && s.lag ? s.lag : null;
        if (!state.framesKnown && s.frames_processed > 0) {
          state.frames.processed = s.frames_processed;
          state.framesKnown = true;
        }
        render();
      }
    } catch (err) {
      showError(err);
    }
  }

  // ----- controls and status text -----------------------------------------------------------------------------
  const statusEl = document.getElementById("status");

  const banner = document.getElementById("banner");
  const legends = {
    vein: document.getElementById("vein-legend"),
    force: document.getElementById("force-legend"),
    coverage: document.getElementById("coverage-legend"),
  };

  function statusText() {
    const f = state.frames;
    let text = state.status;
    if (!state.framesKnown || (state.status === "done" && f.processed === 0 && (state.loading || !state.dzi))) {
      // never "done · 0 frames processed" while the results are still on their way
      text += state.status === "receiving" && !state.dzi ? " · waiting for the first frames" : " · loading results…";
    } else {
      text += " · " + f.processed + " frames processed (" + f.ok + " placed, ";
      // placed frames tracked on a keyframe without features (the service fell behind its uploads): only when any
      if (f.tracked) text += f.tracked + " of them tracked, ";
      text += f.lost + " lost";
      const rejected = f.rejected - (f.no_contact || 0);
      text += rejected ? ", " + rejected + " rejected)" : ")";
      if (f.no_contact) text += " · " + f.no_contact + " off the skin";
      // frames placed on a fragment of the map that has not joined it yet: they appear once it joins
      if (f.in_fragments) text += " · " + f.in_fragments + (state.status === "done" ? " in unjoined fragments" : " waiting in fragments");
    }
    if (state.received !== null) text += " · " + state.received + " received";
    if (state.lag && state.status !== "done") {
      // upload-to-placement lag of the newest frames (the session state's p50/p95), live only
      text += " · lag " + state.lag.p50_s.toFixed(1) + " s (p95 " + state.lag.p95_s.toFixed(1) + " s)";
    }
    if (state.measure.active) {
      text += state.measure.mm !== null ? " · distance " + state.measure.mm.toFixed(1) + " mm" : " · click two points to measure";
    }
    if (state.error) text += " · " + state.error;
    return text;
  }

  function render() {
    statusEl.textContent = statusText();
    statusEl.title = statusEl.textContent;
    statusEl.classList.toggle("error", Boolean(state.error) && !state.error.startsWith("reconnecting"));
    for (const [name, el] of Object.entries(legends)) el.hidden = state.layer !== name;
    const messages = state.warnings.map((w) => w.message);
    if (state.status === "failed" && !state.warnings.some((w) => w.code === "processing_failed")) {
      messages.unshift("Processing failed: the results may be incomplete.");
    }
    banner.textContent = messages.map((m) => "⚠ " + m).join("\n");
    banner.hidden = messages.length === 0;
  }

  function showError(err) {
    state.error = err && err.message ? err.message : String(err);
    render();
  }

  document.querySelectorAll('input[name="layer"]').forEach(function (input) {
    input.addEventListener("change", function () {
      if (!input.checked || input.value === state.layer) return;
      state.layer = input.value;
      refreshTiles();
      render();
    });
  });
  document.getElementById("show-path").addEventListener("change", function (e) {
    svg.classList.toggle("hidden", !e.target.checked);
  });
  document.getElementById("fit").addEventListener("click", function () {
    state.userMoved = false;
    fitToExtent(false);
  });

  window.veinmosaicViewer = {
    viewer: viewer,
    revisions: revisions,
    state: state,
    refresh: refreshTiles,
    fit: fitToExtent,
    dziPoint: dziPoint,
    measure: setMeasuring,
    frameText: frameText,
    currentItem: function () {
      return current;
    },
    idle: function () {
      return current !== null && pending === null && !state.loading && !dirty && current.getFullyLoaded();
    },
  };

  render();
  connect();
  pollSession();
  window.setInterval(function () {
    if (!state.done) pollSession();
  }, SESSION_POLL_MS);
})();
