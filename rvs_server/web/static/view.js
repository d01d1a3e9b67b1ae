// RVS web view. Plain JavaScript, no framework, nothing from another host: the page talks only to
// the server that served it (/api/status, /api/products, /products/NAME/FILE, /events).
//
// Live and cheap: events are queued as they arrive and the page is redrawn at most once a frame
// (requestAnimationFrame), so a job publishing 50 events a second costs one redraw per frame; every
// list the page keeps is capped, so it can stay open for days.
"use strict";

(function () {
  const TOKEN = new URLSearchParams(window.location.search).get("token");
  const EVENT_LINES = 300;        // event lines shown
  const EVENT_KEEP = 1000;        // events kept (for re-filtering)
  const PRODUCTS = 12;            // newest products listed
  const THUMBS = 6;               // pictures per product
  const HAZARDS = 100;            // hazard detections kept on the map
  const TRACK = 200;              // tracked target positions kept
  const PATH_POINTS = 5000;       // points per path
  const TOPICS = ["mode", "progress", "product", "navigate", "hazard", "guard", "track", "log", "dropped"];

  // ---------------------------------------------------------------------------------- requests
  function url(path) {  // the page's token goes on to every request it makes
    if (!TOKEN) return path;
    return path + (path.indexOf("?") < 0 ? "?" : "&") + "token=" + encodeURIComponent(TOKEN);
  }
  function productUrl(name, file) {
    return url("/products/" + encodeURIComponent(name) + "/" + file.split("/").map(encodeURIComponent).join("/"));
  }
  function getJSON(path) {
    return fetch(url(path), { cache: "no-store", credentials: "same-origin" }).then(function (r) {
      if (!r.ok) throw new Error(path + ": HTTP " + r.status);
      return r.json();
    });
  }
  function getText(path) {
    return fetch(url(path), { cache: "no-store", credentials: "same-origin" }).then(function (r) {
      if (!r.ok) throw new Error(path + ": HTTP " + r.status);
      return r.text();
    });
  }
  const $ = function (id) { return document.getElementById(id); };
  function el(tag, cls, text) {
    const e = document.createElement(tag);
    if (cls) e.className = cls;
    if (text !== undefined && text !== null) e.textContent = String(text);
    return e;
  }
  function num(v) { const x = parseFloat(v); return Number.isFinite(x) ? x : null; }
  function pair(text) {  // "X,Y" -> [x, y] or null
    if (typeof text !== "string") return null;
    const p = text.split(",").map(num);
    return p.length >= 2 && p[0] !== null && p[1] !== null ? [p[0], p[1]] : null;
  }
  function pushCapped(list, item, cap) { list.push(item); if (list.length > cap) list.splice(0, list.length - cap); }

  // ---------------------------------------------------------------------------------- state
  const state = {
    status: {}, statusAt: 0,
    progress: { job: null, command: null, percent: 0, message: "" },
    events: [], pending: [], eventsDirty: false, rebuildEvents: false,
    hidden: new Set(),
    dropped: null,
    products: [],
    map: null,          // {product, file, grid, image, src: [sx, sy, sw, sh]}
    nav: newTraverse(null),
    hazards: [], track: [],
    dirty: { header: true, status: true, events: true, products: true, map: true },
  };
  function newTraverse(job) {
    return { job: job, goal: null, planned: [], driven: [], pose: null, fromProduct: null, live: false };
  }

  // ---------------------------------------------------------------------------------- drawing, coalesced
  let frameAsked = false;
  function redraw(part) {
    state.dirty[part] = true;
    if (!frameAsked) { frameAsked = true; window.requestAnimationFrame(frame); }
  }
  function frame() {
    frameAsked = false;
    const d = state.dirty;
    state.dirty = {};
    if (d.header) drawHeader();
    if (d.status) drawStatus();
    if (d.events) drawEvents();
    if (d.products) drawProducts();
    if (d.map) drawMap();
  }

  function drawHeader() {
    const s = state.status, p = state.progress;
    const mode = s.mode || "?";
    const m = $("mode");
    m.textContent = mode;
    m.className = "mode " + mode;
    // The last job stays in view after it ended, so its 100 % and final message still make sense.
    const ended = p.job && s.job === "none";
    $("job").textContent = p.job ? p.job + (ended ? " (ended)" : "") : (s.job || "?");
    $("command").textContent = p.command || s.command || "?";
    const percent = Math.max(0, Math.min(100, num(p.percent) || 0));
    $("bar-fill").style.width = percent + "%";
    $("bar-text").textContent = Math.round(percent) + " %";
    $("progress-message").textContent = p.message || "\u00a0";
    $("progress-message").title = p.message || "";
  }

  function healthClass(v) { return v === "ok" ? "h-ok" : v === "fault" ? "h-fault" : v === "off" ? "h-off" : "h-other"; }
  function drawStatus() {
    const s = state.status;
    const devices = $("devices").tBodies[0];
    devices.replaceChildren();
    Object.keys(s).filter(function (k) { return k.indexOf("dev.") === 0; }).sort().forEach(function (k) {
      const tr = el("tr");
      tr.append(el("td", null, k.slice(4)), el("td", healthClass(s[k]), s[k]));
      devices.append(tr);
    });
    if (!devices.rows.length) devices.append(rowOf("no status yet", ""));
    $("pan").textContent = s.pan === undefined ? "?" : s.pan;
    $("tilt").textContent = s.tilt === undefined ? "?" : s.tilt;
    const acts = $("activities").tBodies[0];
    acts.replaceChildren();
    ["hazard", "track", "recovery", "uptime", "version"].forEach(function (k) {
      if (s[k] !== undefined) acts.append(rowOf(k, s[k]));
    });
    $("status-age").textContent = state.statusAt ? "status at " + new Date(state.statusAt).toLocaleTimeString() : "";
  }
  function rowOf(a, b) { const tr = el("tr"); tr.append(el("td", null, a), el("td", "mono", b)); return tr; }

  // ---------------------------------------------------------------------------------- events list
  function eventText(e) {
    const d = e.data || {};
    if (e.topic === "progress") return (d.job ? "job " + d.job + " " : "") + (d.command || "") + " " + d.percent + "% " + (d.message || "");
    if (e.topic === "log") return (d.level || "") + " " + (d.source || "") + ": " + (d.message || "");
    if (e.topic === "dropped") return d.count + " events dropped by the server for this page (" + d.total + " in all): it read too slowly";
    return Object.keys(d).map(function (k) { return k + "=" + (typeof d[k] === "object" ? JSON.stringify(d[k]) : d[k]); }).join(" ");
  }
  function eventLine(e) {
    const li = el("li", "t-" + e.topic.replace(/[^a-z0-9_-]/gi, ""));
    li.append(el("span", "time", e.time), el("span", "topic", e.topic), document.createTextNode(e.text));
    li.title = e.text;
    return li;
  }
  function ensureTopic(topic) {
    if (document.getElementById("topic-" + topic)) return;
    const label = el("label");
    const box = el("input");
    box.type = "checkbox"; box.id = "topic-" + topic; box.checked = !state.hidden.has(topic);
    box.addEventListener("change", function () {
      if (box.checked) state.hidden.delete(topic); else state.hidden.add(topic);
      state.rebuildEvents = true;
      redraw("events");
    });
    label.append(box, document.createTextNode(" " + topic));
    $("topics").append(label);
  }
  function drawEvents() {
    const list = $("events");
    if (state.rebuildEvents) {
      state.rebuildEvents = false;
      state.pending = [];
      const shown = [];
      for (let i = state.events.length - 1; i >= 0 && shown.length < EVENT_LINES; i--) {
        if (!state.hidden.has(state.events[i].topic)) shown.push(eventLine(state.events[i]));
      }
      list.replaceChildren.apply(list, shown);
    } else if (state.pending.length) {
      const batch = state.pending.filter(function (e) { return !state.hidden.has(e.topic); }).slice(-EVENT_LINES);
      state.pending = [];
      const frag = document.createDocumentFragment();
      for (let i = batch.length - 1; i >= 0; i--) frag.append(eventLine(batch[i]));  // newest first
      list.prepend(frag);
      while (list.childElementCount > EVENT_LINES) list.lastElementChild.remove();
    }
    $("event-count").textContent = list.childElementCount + " shown";
    const notice = $("dropped");
    if (state.dropped) {
      notice.hidden = false;
      notice.textContent = "The server dropped " + state.dropped.total + " events for this page (the last " +
        state.dropped.count + " at " + state.dropped.time + "): progress is coalesced, other events were lost.";
    }
  }

  // ---------------------------------------------------------------------------------- status and products
  let statusBusy = false, statusAgain = false;
  function refreshStatus() {
    if (statusBusy) { statusAgain = true; return; }
    statusBusy = true;
    getJSON("/api/status").then(function (s) {
      state.status = s; state.statusAt = Date.now();
      if (s.job !== "none" && state.progress.job !== s.job) {
        state.progress = { job: s.job, command: s.command, percent: num(s.percent) || 0, message: "" };
      }
      markEnded();
      redraw("status"); redraw("header");
    }).catch(function (err) { console.warn(err); }).finally(function () {
      statusBusy = false;
      if (statusAgain) { statusAgain = false; window.setTimeout(refreshStatus, 300); }
    });
  }
  // A job's last progress line is rarely 100 % (navigate stops at 98 when it arrives): once the job has
  // ended and its product is complete, the bar says so, instead of staying at the last figure.
  function markEnded() {
    const p = state.progress, s = state.status;
    if (!p.job || s.job !== "none" || s.mode === "busy" || num(p.percent) >= 100) return false;
    const done = state.products.find(function (q) { return String(q.job) === String(p.job) && q.status === "complete"; });
    if (!done) return false;
    state.progress = { job: p.job, command: p.command, percent: 100, message: "done: product " + done.name };
    return true;
  }
  let productsTimer = 0;
  function refreshProductsSoon() {
    if (productsTimer) return;
    productsTimer = window.setTimeout(function () { productsTimer = 0; refreshProducts(); }, 400);
  }
  function refreshProducts() {
    getJSON("/api/products?limit=" + PRODUCTS).then(function (r) {
      state.products = Array.isArray(r.products) ? r.products : [];
      if (markEnded()) redraw("header");
      chooseMap();
      loadTraverseProduct();
      redraw("products");
    }).catch(function (err) { $("products-note").textContent = String(err.message || err); });
  }

  function pngs(p) {  // a product's pictures, most telling first, newest cycle first
    const rank = ["overview", "ortho", "hazard", "dem", "plan", "plan-ortho", "route", "hop"];
    const files = Object.keys(p.files || {}).filter(function (f) { return /\.png$/i.test(f) && f.indexOf("truth/") < 0; });
    function key(f) {
      const parts = f.split("/"), base = parts[parts.length - 1].replace(/\.png$/i, "");
      const cycle = parts.length > 1 ? -(parseInt((parts[0].match(/\d+/) || ["0"])[0], 10) || 0) : -1e6;
      let r = rank.indexOf(base); if (r < 0) r = rank.length;
      return [cycle, r, f];
    }
    return files.map(key).sort(function (a, b) { return a[0] - b[0] || a[1] - b[1] || (a[2] < b[2] ? -1 : 1); })
      .map(function (k) { return k[2]; });
  }
  function drawProducts() {
    const box = $("products");
    box.replaceChildren();
    if (!state.products.length) { box.append(el("div", "empty", "no products yet")); return; }
    state.products.forEach(function (p) {
      const card = el("div", "product");
      const name = el("div", "name", p.name); name.title = p.name;
      const when = p.finished || p.created || "";
      const meta = el("div", "meta");
      meta.append(document.createTextNode((p.command || "?") + " \u00b7 " + when.replace("T", " ").replace(/[+-]\d{4}$/, "") + " \u00b7 "),
        el("span", "status-" + (p.status || "unknown"), p.status || "?"));
      const thumbs = el("div", "thumbs");
      const pictures = pngs(p);
      pictures.slice(0, THUMBS).forEach(function (f) {
        const a = el("a"); a.href = productUrl(p.name, f); a.target = "_blank"; a.rel = "noopener"; a.title = f;
        const img = el("img"); img.loading = "lazy"; img.alt = f; img.src = a.href;
        a.append(img, el("span", null, f));
        thumbs.append(a);
      });
      if (pictures.length > THUMBS) thumbs.append(el("span", "small", "+" + (pictures.length - THUMBS) + " more"));
      card.append(name, meta, thumbs);
      box.append(card);
    });
    $("products-note").textContent = state.products.length + " newest";
  }

  // ---------------------------------------------------------------------------------- the map
  // The newest product with a gridded picture: NAME.png beside a NAME.tif whose grid is in product.json,
  // or a picture drawn on the grid of a GeoTIFF of another name (hop-map: map.png on hops-per-cell.tif).
  const PICTURE_OF = { "hops-per-cell.tif": "map.png" };
  function pictureOf(p, tif) {
    const files = p.files || {}, same = tif.replace(/\.tiff?$/i, ".png");
    if (files[same] !== undefined) return same;
    const base = tif.split("/").pop(), other = PICTURE_OF[base];
    const path = other ? tif.slice(0, tif.length - base.length) + other : null;
    return path && files[path] !== undefined ? path : null;
  }
  function chooseMap() {
    const rank = ["ortho", "hazard", "dem"];
    for (const p of state.products) {
      const grids = p.grids || {};
      const candidates = Object.keys(grids).filter(function (t) {
        return t.indexOf("truth/") < 0 && pictureOf(p, t) !== null;
      });
      if (!candidates.length) continue;
      candidates.sort(function (a, b) {
        const ca = a.split("/").length > 1 ? a.split("/")[0] : "", cb = b.split("/").length > 1 ? b.split("/")[0] : "";
        if (ca !== cb) return ca < cb ? 1 : -1;   // newest cycle first
        const ra = rank.indexOf(a.split("/").pop().replace(/\.tiff?$/i, "")), rb = rank.indexOf(b.split("/").pop().replace(/\.tiff?$/i, ""));
        return (ra < 0 ? 99 : ra) - (rb < 0 ? 99 : rb);
      });
      const tif = candidates[0], file = pictureOf(p, tif);
      if (state.map && state.map.product === p.name && state.map.file === file) return;
      const map = { product: p.name, file: file, grid: grids[tif], image: null, src: null };
      const img = new Image();
      img.onload = function () { map.image = img; map.src = mapRegion(img, map.grid); redraw("map"); };
      img.src = productUrl(p.name, file);
      state.map = map;
      $("map-source").textContent = p.name + "/" + file;
      redraw("map");
      return;
    }
  }
  // RVS's map pictures are the grid north up, enlarged by a whole factor (to 480 px at least, the hop
  // maps to 640), under a 22 px title strip and above a legend strip (toolbox/colour.py): the part that
  // is the grid.
  function mapRegion(img, grid) {
    const w = img.naturalWidth, h = img.naturalHeight;
    if (w === grid.cols && h === grid.rows) return [0, 0, w, h];
    const factors = [480, 640].map(function (size) { return Math.max(1, Math.ceil(size / Math.max(grid.rows, grid.cols))); });
    const exact = factors.find(function (f) { return grid.cols * f === w && 22 + grid.rows * f <= h; });
    const f = exact || factors[0];
    if (grid.cols * f <= w && 22 + grid.rows * f <= h) return [0, 22, grid.cols * f, grid.rows * f];
    const g = Math.max(1, Math.floor(w / grid.cols));
    return [0, Math.max(0, Math.min(22, h - grid.rows * g)), grid.cols * g, Math.min(h, grid.rows * g)];
  }

  function drawMap() {
    const canvas = $("map");
    const ratio = window.devicePixelRatio || 1;
    const cssW = canvas.clientWidth || 640, cssH = canvas.clientHeight || 480;
    if (canvas.width !== Math.round(cssW * ratio) || canvas.height !== Math.round(cssH * ratio)) {
      canvas.width = Math.round(cssW * ratio); canvas.height = Math.round(cssH * ratio);
    }
    const ctx = canvas.getContext("2d");
    ctx.setTransform(ratio, 0, 0, ratio, 0, 0);
    ctx.fillStyle = "#0c0e11"; ctx.fillRect(0, 0, cssW, cssH);

    // What is to be seen decides the view: the map, the paths, the goal, the markers.
    const nav = state.nav, map = state.map;
    const pts = [];
    if (map) {
      const g = map.grid;
      pts.push([g.origin[0], g.origin[1]], [g.origin[0] + g.cols * g.cell, g.origin[1] + g.rows * g.cell]);
    }
    nav.planned.concat(nav.driven).forEach(function (p) { pts.push(p); });
    if (nav.goal) pts.push(nav.goal);
    if (nav.pose) pts.push(nav.pose);
    state.hazards.forEach(function (h) { pts.push(h); });
    state.track.forEach(function (t) { pts.push(t); });
    if (!pts.length) {
      ctx.fillStyle = "#8b95a3"; ctx.font = "13px system-ui, sans-serif";
      ctx.fillText("no map yet: a mapping, navigate or hop product with a grid appears here", 14, 24);
      $("map-note").textContent = "";
      exposeDrawn(canvas, null, null);
      return;
    }
    let x0 = Infinity, y0 = Infinity, x1 = -Infinity, y1 = -Infinity;
    pts.forEach(function (p) { x0 = Math.min(x0, p[0]); x1 = Math.max(x1, p[0]); y0 = Math.min(y0, p[1]); y1 = Math.max(y1, p[1]); });
    const pad = Math.max(0.5, 0.05 * Math.max(x1 - x0, y1 - y0));
    x0 -= pad; x1 += pad; y0 -= pad; y1 += pad;
    const scale = Math.min(cssW / (x1 - x0), cssH / (y1 - y0));
    const ox = (cssW - scale * (x1 - x0)) / 2, oy = (cssH - scale * (y1 - y0)) / 2;
    const X = function (x) { return ox + (x - x0) * scale; };
    const Y = function (y) { return cssH - oy - (y - y0) * scale; };   // north up

    if (map && map.image && map.src) {
      const g = map.grid, s = map.src;
      ctx.imageSmoothingEnabled = false;
      ctx.drawImage(map.image, s[0], s[1], s[2], s[3], X(g.origin[0]), Y(g.origin[1] + g.rows * g.cell),
        g.cols * g.cell * scale, g.rows * g.cell * scale);
    }
    drawGrid(ctx, x0, x1, y0, y1, X, Y, scale, cssW, cssH);

    function line(points, colour, width, dash) {
      if (points.length < 2) return;
      ctx.beginPath(); ctx.strokeStyle = colour; ctx.lineWidth = width; ctx.setLineDash(dash || []);
      points.forEach(function (p, i) { if (i) ctx.lineTo(X(p[0]), Y(p[1])); else ctx.moveTo(X(p[0]), Y(p[1])); });
      ctx.stroke(); ctx.setLineDash([]);
    }
    function dot(p, r, colour) { ctx.beginPath(); ctx.fillStyle = colour; ctx.arc(X(p[0]), Y(p[1]), r, 0, 2 * Math.PI); ctx.fill(); }
    line(state.track, "rgba(224, 82, 255, .6)", 1.5);
    line(nav.driven, "#000000", 5);
    line(nav.driven, "#ffffff", 2.5);
    line(nav.planned, "#ffd33d", 2, [6, 4]);
    nav.planned.forEach(function (p) { dot(p, 3, "#ffd33d"); });
    state.hazards.forEach(function (h, i) {
      const a = 0.3 + 0.7 * (i + 1) / state.hazards.length, x = X(h[0]), y = Y(h[1]);
      ctx.strokeStyle = "rgba(255, 140, 0, " + a + ")"; ctx.lineWidth = 2.5;
      ctx.beginPath(); ctx.moveTo(x - 5, y - 5); ctx.lineTo(x + 5, y + 5); ctx.moveTo(x + 5, y - 5); ctx.lineTo(x - 5, y + 5); ctx.stroke();
    });
    if (state.track.length) {
      const t = state.track[state.track.length - 1];
      dot(t, 7, "#e052ff");
      ctx.strokeStyle = "#ffffff"; ctx.lineWidth = 1.5; ctx.beginPath(); ctx.arc(X(t[0]), Y(t[1]), 7, 0, 2 * Math.PI); ctx.stroke();
    }
    if (nav.goal) {
      const gx = X(nav.goal[0]), gy = Y(nav.goal[1]);
      ctx.strokeStyle = "#f85149"; ctx.lineWidth = 3;
      ctx.beginPath(); ctx.arc(gx, gy, 9, 0, 2 * Math.PI); ctx.stroke();
      ctx.beginPath(); ctx.moveTo(gx - 13, gy); ctx.lineTo(gx + 13, gy); ctx.moveTo(gx, gy - 13); ctx.lineTo(gx, gy + 13); ctx.stroke();
    }
    if (nav.pose) {
      const px = X(nav.pose[0]), py = Y(nav.pose[1]), h = nav.pose[2];
      ctx.save(); ctx.translate(px, py);
      if (h !== null && h !== undefined) ctx.rotate(-h);
      ctx.beginPath(); ctx.moveTo(13, 0); ctx.lineTo(-8, 8); ctx.lineTo(-4, 0); ctx.lineTo(-8, -8); ctx.closePath();
      ctx.fillStyle = "#58a6ff"; ctx.fill(); ctx.strokeStyle = "#ffffff"; ctx.lineWidth = 1.5; ctx.stroke();
      if (h === null || h === undefined) { ctx.beginPath(); ctx.arc(0, 0, 6, 0, 2 * Math.PI); ctx.fill(); }
      ctx.restore();
    }
    const notes = [];
    if (nav.pose) notes.push("rover " + nav.pose[0].toFixed(2) + ", " + nav.pose[1].toFixed(2) + (nav.pose[2] !== null ? " @ " + (nav.pose[2] * 180 / Math.PI).toFixed(0) + "\u00b0" : ""));
    if (nav.goal) notes.push("goal " + nav.goal[0].toFixed(2) + ", " + nav.goal[1].toFixed(2));
    if (nav.fromProduct) notes.push("path of " + nav.fromProduct);
    else if (nav.live) notes.push("navigate job " + nav.job + " live");
    $("map-note").textContent = notes.join(" \u00b7 ");
    exposeDrawn(canvas, X, Y);
  }
  // What the map shows, in data attributes of the canvas (canvas pixels, CSS px): for the browser tests,
  // which may not run scripts in the page (its policy), and for anyone inspecting the page.
  function exposeDrawn(canvas, X, Y) {
    const nav = state.nav, map = state.map, ds = canvas.dataset;
    function px(points) {
      if (!X) return "";
      const step = Math.max(1, Math.ceil(points.length / 200));
      return points.filter(function (p, i) { return i % step === 0 || i === points.length - 1; })
        .map(function (p) { return Math.round(X(p[0])) + "," + Math.round(Y(p[1])); }).join(" ");
    }
    function xy(p) { return p ? p[0].toFixed(2) + "," + p[1].toFixed(2) : ""; }
    ds.map = map && map.image ? map.product + "/" + map.file : "";
    ds.driven = String(nav.driven.length);
    ds.planned = String(nav.planned.length);
    ds.goal = xy(nav.goal);
    ds.pose = xy(nav.pose);
    ds.drivenPx = px(nav.driven);
    ds.plannedPx = px(nav.planned);
    ds.source = nav.fromProduct ? "product " + nav.fromProduct : nav.live ? "live " + nav.job : "";
  }
  function drawGrid(ctx, x0, x1, y0, y1, X, Y, scale, w, h) {
    const spans = [0.5, 1, 2, 5, 10, 20, 50, 100];
    let step = spans[spans.length - 1];
    for (const s of spans) { if (s * scale >= 60) { step = s; break; } }
    ctx.strokeStyle = "rgba(255,255,255,.10)"; ctx.lineWidth = 1; ctx.fillStyle = "rgba(255,255,255,.45)";
    ctx.font = "10px system-ui, sans-serif";
    ctx.beginPath();
    for (let x = Math.ceil(x0 / step) * step; x <= x1; x += step) { ctx.moveTo(X(x), 0); ctx.lineTo(X(x), h); }
    for (let y = Math.ceil(y0 / step) * step; y <= y1; y += step) { ctx.moveTo(0, Y(y)); ctx.lineTo(w, Y(y)); }
    ctx.stroke();
    for (let x = Math.ceil(x0 / step) * step; x <= x1; x += step) ctx.fillText(+x.toFixed(2) + " m", X(x) + 2, h - 4);
    for (let y = Math.ceil(y0 / step) * step; y <= y1; y += step) ctx.fillText(+y.toFixed(2), 3, Y(y) - 2);
    ctx.fillText("N \u2191", w - 28, 14);
  }

  // The traverse of a finished navigate: its path.csv (estimated path), goal and waypoints.
  let traverseLoading = null;
  function loadTraverseProduct() {
    if (state.nav.live) return;
    const p = state.products.find(function (q) { return q.command === "navigate" && (q.files || {})["path.csv"] !== undefined; });
    if (!p || state.nav.fromProduct === p.name || traverseLoading === p.name) return;
    traverseLoading = p.name;
    getText("/products/" + encodeURIComponent(p.name) + "/path.csv").then(function (text) {
      if (state.nav.live) return;
      const rows = text.trim().split(/\r?\n/);
      const head = rows.shift().split(",");
      const ix = head.indexOf("x"), iy = head.indexOf("y"), ih = head.indexOf("heading_deg");
      const driven = [];
      rows.forEach(function (r) {
        const c = r.split(","), x = num(c[ix]), y = num(c[iy]);
        if (x !== null && y !== null) driven.push([x, y, ih >= 0 ? (num(c[ih]) || 0) * Math.PI / 180 : null]);
      });
      const nav = newTraverse(p.job || null);
      nav.fromProduct = p.name;
      nav.driven = driven.slice(-PATH_POINTS).map(function (q) { return [q[0], q[1]]; });
      nav.pose = driven.length ? driven[driven.length - 1] : null;
      const to = (p.arguments || {}).to;
      if (Array.isArray(to) && to.length >= 2) nav.goal = [num(to[0]), num(to[1])];
      state.nav = nav;
      redraw("map");
    }).catch(function (err) { console.warn(err); }).finally(function () { traverseLoading = null; });
  }

  // ---------------------------------------------------------------------------------- live events
  const START = /^job (\d+) start: navigate (.*)$/;
  const DRIVING = /driving to \((-?[\d.]+), (-?[\d.]+)\)/;
  function startTraverse(job, line) {
    const nav = newTraverse(job), before = state.nav.pose;
    nav.live = true;
    if (before) { nav.pose = before; nav.driven.push([before[0], before[1]]); }  // it starts where the last one ended
    const to = /--to[ =](\S+)/.exec(line);
    if (to) nav.goal = pair(to[1]);
    state.nav = nav;
    redraw("map");
  }
  function onNavigateProgress(d) {
    let nav = state.nav;
    if (!nav.live || nav.job !== d.job) { startTraverse(d.job, ""); nav = state.nav; }
    const m = DRIVING.exec(d.message || "");
    if (!m) {
      if (/waiting for the GNC|started/.test(d.message || "")) return;
      // Mapping or planning again after a drive: the leg announced last has been driven.
      const end = nav.planned[nav.planned.length - 1], at = nav.pose;
      if (end && (!at || at[0] !== end[0] || at[1] !== end[1])) {
        nav.pose = [end[0], end[1], at ? Math.atan2(end[1] - at[1], end[0] - at[0]) : null];
        pushCapped(nav.driven, [end[0], end[1]], PATH_POINTS);
        redraw("map");
      }
      return;
    }
    const target = [num(m[1]), num(m[2])];
    const last = nav.planned[nav.planned.length - 1];
    if (last && last[0] === target[0] && last[1] === target[1]) return;
    // A new leg begins where the last one ended: the rover has reached the previous target.
    if (last) { nav.pose = [last[0], last[1], Math.atan2(target[1] - last[1], target[0] - last[0])]; }
    const tail = nav.driven[nav.driven.length - 1];
    if (nav.pose && !(tail && tail[0] === nav.pose[0] && tail[1] === nav.pose[1])) {
      pushCapped(nav.driven, [nav.pose[0], nav.pose[1]], PATH_POINTS);
    }
    pushCapped(nav.planned, target, PATH_POINTS);
    redraw("map");
  }
  function onNavigateEvent(d) {  // the GNC's hand-outs: waypoints and goal, or one action
    let nav = state.nav;
    if (!nav.live || (d.job && nav.job !== d.job)) { startTraverse(d.job || null, ""); nav = state.nav; }
    if (d.goal) nav.goal = pair(d.goal) || nav.goal;
    if (d.waypoints) {
      const wps = String(d.waypoints).split(/\s+/).map(pair).filter(Boolean);
      if (nav.pose) { pushCapped(nav.driven, [nav.pose[0], nav.pose[1]], PATH_POINTS); }
      nav.planned = wps.slice(0, PATH_POINTS);
    }
    redraw("map");
  }

  function onEvent(e) {
    const d = e.data || {};
    const now = new Date();
    e.time = now.toLocaleTimeString();
    e.text = eventText(e);
    pushCapped(state.events, e, EVENT_KEEP);
    state.pending.push(e);
    if (state.pending.length > EVENT_LINES) state.pending.splice(0, state.pending.length - EVENT_LINES);
    ensureTopic(e.topic);
    redraw("events");
    switch (e.topic) {
      case "progress":
        state.progress = { job: d.job, command: d.command, percent: num(d.percent) || 0, message: d.message || "" };
        if (state.status.job !== d.job) state.status.job = d.job;
        if (d.command === "navigate") onNavigateProgress(d);
        if (num(d.percent) >= 100 || /move-ptu|ptu/.test(d.command || "")) refreshStatusSoon();
        redraw("header");
        break;
      case "mode":
        state.status.mode = d.mode;
        if (d.mode !== "busy") { state.nav.live = false; }
        redraw("header");
        refreshStatusSoon();
        break;
      case "product":
        refreshProductsSoon();
        break;
      case "log": {
        const m = START.exec(d.message || "");
        if (m) startTraverse(m[1], m[2]);
        break;
      }
      case "navigate":
        onNavigateEvent(d);
        break;
      case "hazard": {
        const x = num(d.x), y = num(d.y);
        if (d.state === "hazard" && x !== null && y !== null) { pushCapped(state.hazards, [x, y], HAZARDS); redraw("map"); }
        break;
      }
      case "track": {
        const x = num(d.x), y = num(d.y);
        if (x !== null && y !== null) { pushCapped(state.track, [x, y], TRACK); redraw("map"); }
        break;
      }
      case "dropped":
        state.dropped = { count: d.count, total: d.total, time: e.time };
        break;
    }
  }
  let statusSoon = 0;
  function refreshStatusSoon() {
    if (statusSoon) return;
    statusSoon = window.setTimeout(function () { statusSoon = 0; refreshStatus(); }, 250);
  }

  // One stream, reopened after any error with a growing pause (a restarting server, a 503).
  let source = null, retry = 1000, retryTimer = 0;
  function connect() {
    retryTimer = 0;
    const link = $("link");
    link.textContent = "connecting"; link.className = "link down";
    source = new EventSource(url("/events"));
    source.onopen = function () {
      retry = 1000;
      link.textContent = "live"; link.className = "link up";
      refreshStatus(); refreshProducts();   // whatever happened while the stream was down
    };
    source.onmessage = function (m) {
      let e;
      try { e = JSON.parse(m.data); } catch (err) { return; }
      if (e && typeof e.topic === "string") onEvent(e);
    };
    source.onerror = function () {
      source.close();
      link.textContent = "reconnecting"; link.className = "link down";
      if (!retryTimer) retryTimer = window.setTimeout(connect, retry);
      retry = Math.min(retry * 2, 15000);
    };
  }

  // ------------------------------------------------------------------------------ command box
  // The line goes through the server's one dispatcher (POST /api/command), as a text client's would;
  // its reply is shown when it comes (a job's, at its end), its progress meanwhile in the bar above.
  const COMMAND_REPLIES = 50, HISTORY = 100;
  const history = [];
  let historyAt = 0;
  function showReply(text, cls) {
    const list = $("command-replies");
    const item = el("li", cls, text);
    list.append(item);
    while (list.children.length > COMMAND_REPLIES) list.firstChild.remove();
    list.scrollTop = list.scrollHeight;
    return item;
  }
  function sendCommand(line) {
    showReply("> " + line, "sent");
    return fetch(url("/api/command"), {
      method: "POST", cache: "no-store", credentials: "same-origin",
      headers: { "Content-Type": "application/json" }, body: JSON.stringify({ line: line }),
    }).then(function (r) {
      return r.json().then(function (body) {
        if (body.reply) { showReply(body.reply, body.ok ? "ok" : "err"); return body; }
        showReply("HTTP " + r.status + " " + (body.message || body.error || ""), "err");
        return body;
      });
    }).catch(function (err) { showReply("no reply: " + (err.message || err), "err"); })
      .finally(function () { refreshStatusSoon(); refreshProductsSoon(); });
  }
  $("command-form").addEventListener("submit", function (ev) {
    ev.preventDefault();
    const input = $("command-line"), line = input.value.trim();
    if (!line) return;
    if (history[history.length - 1] !== line) pushCapped(history, line, HISTORY);
    historyAt = history.length;
    input.value = "";
    sendCommand(line);
  });
  $("command-line").addEventListener("keydown", function (ev) {  // up and down walk the history, as in a shell
    if (ev.key !== "ArrowUp" && ev.key !== "ArrowDown") return;
    ev.preventDefault();
    historyAt = Math.max(0, Math.min(history.length, historyAt + (ev.key === "ArrowUp" ? -1 : 1)));
    this.value = history[historyAt] || "";
  });

  TOPICS.forEach(ensureTopic);
  window.addEventListener("resize", function () { redraw("map"); });
  refreshStatus();
  refreshProducts();
  window.setInterval(refreshStatus, 5000);   // uptime, devices and angles that no event announces
  connect();
  redraw("header"); redraw("status"); redraw("events"); redraw("products"); redraw("map");
  window.rvsView = state;   // for the browser tests and for a curious operator's console
})();
