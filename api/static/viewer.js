/*
 * veinmosaic browser viewer: the Deep Zoom mosaic of one session, live while the scan goes on.
 *
 * - The session id is the last part of the page path; a view-only token (?token=) is passed on to every
 *   API call (fetch, tile URLs, the EventSource), since a browser cannot add an Authorization header there.
 * - Tiles come from a custom OpenSeadragon tile source built from mosaic.json "dzi"; each tile URL carries
 *   the results version (v) and the tile's revision (rev), so the browser may cache tiles for ever and a
 *   changed tile simply has a new URL.
 * - Server-Sent Events (/events) bring progress: new tile revisions, the tail of the probe path, counters.
 *   Changed tiles are reloaded by double buffering: a new TiledImage with the new revisions is loaded
 *   invisibly on top of the old one (unchanged tiles come from cache) and swapped in when fully loaded.
 * - The probe path is an SVG overlay in DZI pixels: px = dzi.origin_px + mm * px_per_mm.
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
  const token = new URLSearchParams(window.location.search).get("token") || "";
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
    frames: { processed: 0, ok: 0, lost: 0, rejected: 0 },
    received: null,
    path: new Map(), // seq -> [x_mm, y_mm, status]
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

  function refreshTiles() {
    if (!state.dzi) return;
    if (pending) {
      dirty = true;
      return;
    }
    dirty = false;
    const first = current === null;
    state.loading = true;
    viewer.addTiledImage({
      tileSource: makeTileSource(state.layer, state.dzi, state.resultsVersion),
      x: 0,
      y: 0,
      width: 1,
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
  const line = document.createElementNS(SVG_NS, "polyline");
  const marker = document.createElementNS(SVG_NS, "circle");
  marker.setAttribute("r", "5");
  marker.setAttribute("visibility", "hidden");
  group.appendChild(line);
  svg.appendChild(group);
  svg.appendChild(marker);
  viewer.element.appendChild(svg);
  let lastPoint = null;

  function dziPoint(x_mm, y_mm) {
    const d = state.dzi;
    return [d.origin_px[0] + x_mm * state.pxPerMm, d.origin_px[1] + y_mm * state.pxPerMm];
  }

  function drawPath() {
    if (!state.dzi || !state.pxPerMm) return;
    const seqs = Array.from(state.path.keys()).sort((a, b) => a - b);
    const pts = [];
    lastPoint = null;
    for (const seq of seqs) {
      const [x, y, status] = state.path.get(seq);
      if (status !== "ok" || x === null || y === null || !isFinite(x) || !isFinite(y)) continue;
      const p = dziPoint(x, y);
      pts.push(p[0].toFixed(1) + "," + p[1].toFixed(1));
      lastPoint = p;
    }
    line.setAttribute("points", pts.join(" "));
    placeOverlay();
  }

  function placeOverlay() {
    if (!state.dzi) return;
    const W = state.dzi.width;
    const vp = viewer.viewport;
    const p0 = vp.pixelFromPoint(new OpenSeadragon.Point(0, 0), true);
    const p1 = vp.pixelFromPoint(new OpenSeadragon.Point(1, 0), true);
    const s = (p1.x - p0.x) / W; // element px per DZI px
    group.setAttribute("transform", "translate(" + p0.x + "," + p0.y + ") scale(" + s + ")");
    if (lastPoint) {
      marker.setAttribute("cx", String(p0.x + lastPoint[0] * s));
      marker.setAttribute("cy", String(p0.y + lastPoint[1] * s));
      marker.setAttribute("visibility", "visible");
    } else {
      marker.setAttribute("visibility", "hidden");
    }
  }

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
    if (doc.frames) Object.assign(state.frames, doc.frames);
    if (doc.status) state.status = doc.status;
    if (versionChanged) state.path = new Map();
    return true;
  }

  function mergePath(rows) {
    for (const row of rows || []) {
      state.path.set(row[0], [row[1], row[2], row[3]]);
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
    state.path = new Map(rows.map((r) => [r.seq, [r.x_mm, r.y_mm, r.status]]));
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
    for (const k of ["processed", "ok", "lost", "rejected"]) {
      if (data[k] !== undefined) state.frames[k] = data[k];
    }
    if (data.extent_mm !== undefined && data.extent_mm !== null) state.extentMm = data.extent_mm;
    if (data.status) state.status = data.status;
    mergePath(data.path_tail);
    drawPath();
    if (data.path_reset) schedulePathReload();
    if (changed) refreshTiles();
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
        render();
      }
    } catch (err) {
      showError(err);
    }
  }

  // ----- controls and status text -----------------------------------------------------------------------------
  const statusEl = document.getElementById("status");
  const legend = document.getElementById("force-legend");

  function render() {
    const f = state.frames;
    let text = state.status;
    text += " · " + f.processed + " frames processed (" + f.ok + " placed, " + f.lost + " lost";
    text += f.rejected ? ", " + f.rejected + " rejected)" : ")";
    if (state.received !== null) text += " · " + state.received + " received";
    if (state.error) text += " · " + state.error;
    statusEl.textContent = text;
    statusEl.classList.toggle("error", Boolean(state.error) && !state.error.startsWith("reconnecting"));
    legend.hidden = state.layer !== "force";
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
