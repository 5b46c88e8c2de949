// pulsetrack console: the browser side.
//
// One EventSource (/api/events) feeds everything; commands go out as POST /api/command.
// The session cookie is HttpOnly and handled by the browser: any 401 sends us to /login.html.
// Plain ES2020, no framework, no build step. uPlot (vendor/uplot) draws the two line plots.
"use strict";

(() => {
  const $ = (id) => document.getElementById(id);

  // ---------------------------------------------------------------------------------------------
  // constants
  const WINDOW_S = 60;            // displacement plot span
  const KEEP_S = 65;              // ring buffer keeps a little more than the plot shows
  const GAP_S = 0.5;              // samples further apart than this: a gap in the plot
  const RING_CAP = 8192;          // > 65 s at 120 Hz
  const REDRAW_MS = 100;          // plots redraw at most ~10 Hz
  const LINK_SILENCE_MS = 5000;   // no `link` event for this long while the stream is open: "silent"
  const DISP_QUIET_S = 3;         // no deformation sample for this long (daemon live): say so
  const SPECTRUM_MAX_HZ = 3;
  const MIN_DRAG_CSS_PX = 3;      // a press-release shorter than this is a tap, not an ROI
  const DEFAULT_TOLERANCE_MM = 20;

  // feature status codes (features event) -> how they are drawn and counted
  const FEATURE_STATUS = {
    0: { key: "ok", colour: "#3fb950", shape: "circle" },
    1: { key: "occluded", colour: "#f0b429", shape: "circle" },
    2: { key: "lost", colour: "#8792a2", shape: "small" },
    3: { key: "outlier_epipolar", colour: "#ff5b52", shape: "cross" },
    4: { key: "outlier_surface", colour: "#ff5b52", shape: "cross" },
    5: { key: "outlier_triangulation", colour: "#ff5b52", shape: "cross" },
  };
  const ROI_COLOUR = "#ffd84d";
  const ROI_PENDING_COLOUR = "#4fd6ff";
  const AXIS_COLOUR = "#9aa5b4";
  const GRID_COLOUR = "rgba(255,255,255,0.07)";
  // Okabe-Ito colours (colour-blind safe) for dx, dy, dz; the magnitude in light grey, thicker.
  const DISP_SERIES = [
    { label: "dx", stroke: "#56b4e9", width: 1.5 },
    { label: "dy", stroke: "#e69f00", width: 1.5 },
    { label: "dz", stroke: "#cc79a7", width: 1.5 },
    { label: "|d|", stroke: "#e6e9ee", width: 2.2 },
  ];

  // ---------------------------------------------------------------------------------------------
  // state
  const S = {
    stream: "connecting",   // connecting | open | reconnecting
    everOpen: false,
    linkSeen: false,
    daemon: false,
    dds: false,
    linkText: "",
    lastLinkAt: 0,          // performance.now() of the last `link` event (or of the stream's open)
    downSince: 0,           // performance.now() when the stream went down
    mode: "connecting",     // what the banner shows: connecting | live | nodaemon | reconnecting | silent
    fullW: 0, fullH: 0,     // the full camera image (health), features and ROI are in its pixels
    features: null,         // last features event
    roi: null,              // ROI in force: {left, right, depth_tolerance_mm}
    pending: null,          // ROI being edited: {left:[x,y,w,h], right:[x,y,w,h]|null}
    drag: null,             // ROI drag in progress, full-image px
    overlayDirty: true,
    healthSeen: false,
  };
  const sides = {};
  for (const side of ["left", "right"]) {
    sides[side] = {
      side,
      img: $(`${side}-image`),
      overlay: $(`${side}-overlay`),
      view: $(`${side}-view`),
      placeholder: $(`${side}-placeholder`),
      info: $(`${side}-info`),
      wanted: 0,         // newest seq announced
      tried: 0,          // newest seq we attempted
      shown: 0,          // seq on screen
      frame: null,
      loading: false,
      natW: 0, natH: 0,
    };
  }
  // ---------------------------------------------------------------------------------------------
  // helpers
  let leaving = false;
  function toLogin() {
    if (leaving) return;
    leaving = true;
    if (es) es.close();
    location.replace("/login.html");
  }

  // fetch wrapper: JSON in/out, 401 -> login; never throws.
  async function api(method, path, body) {
    const init = { method, credentials: "same-origin", cache: "no-store", headers: {} };
    if (body !== undefined) {
      init.headers["Content-Type"] = "application/json";
      init.body = JSON.stringify(body);
    }
    let r;
    try {
      r = await fetch(path, init);
    } catch (_) {
      return { status: 0, ok: false, data: null, error: "cannot reach the console server" };
    }
    if (r.status === 401) {
      toLogin();
      return { status: 401, ok: false, data: null, error: "not logged in" };
    }
    let data = null;
    try { data = await r.json(); } catch (_) { /* empty or not JSON */ }
    const error = r.ok ? "" : (data && typeof data.error === "string" && data.error) || `HTTP ${r.status}`;
    return { status: r.status, ok: r.ok, data, error };
  }

  const num = (v) => typeof v === "number" && Number.isFinite(v);
  const fmtInt = (v) => (num(v) ? Math.round(v).toLocaleString("en-US") : "—");
  const fmtMs = (us) => (num(us) ? (us / 1000).toFixed(us < 10000 ? 2 : 1) : "—");
  const fmtMm = (v, digits = 2) => (num(v) ? v.toFixed(digits) : "—");
  const str = (v) => (typeof v === "string" && v !== "" ? v : "—");
  const isRect = (r) => Array.isArray(r) && r.length === 4 && r.every(num);

  function setText(id, text) {
    const el = typeof id === "string" ? $(id) : id;
    if (el.textContent !== text) el.textContent = text;
  }

  function fitCanvas(canvas) {
    // Backing store in device pixels; drawing in CSS pixels.
    const r = canvas.getBoundingClientRect();
    const dpr = window.devicePixelRatio || 1;
    const w = Math.max(1, Math.round(r.width * dpr));
    const h = Math.max(1, Math.round(r.height * dpr));
    if (canvas.width !== w || canvas.height !== h) {
      canvas.width = w;
      canvas.height = h;
    }
    const ctx = canvas.getContext("2d");
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    return { ctx, w: r.width, h: r.height };
  }

  // ---------------------------------------------------------------------------------------------
  // link status: banner + header pill + greying
  const banner = $("link-banner");
  const pill = $("link-status");

  function updateLink() {
    const now = performance.now();
    let mode;
    if (S.stream !== "open") mode = S.everOpen ? "reconnecting" : "connecting";
    else if (now - S.lastLinkAt > LINK_SILENCE_MS) mode = "silent";
    else if (!S.linkSeen) mode = "connecting";
    else mode = S.daemon ? "live" : "nodaemon";
    S.mode = mode;

    let title, text, word;
    switch (mode) {
      case "live":
        title = "pulsetrackd live";
        text = S.linkText;
        word = "live";
        break;
      case "nodaemon":
        title = "pulsetrackd NOT SEEN";
        text = [S.linkText, S.dds ? "" : "DDS connection down", lastData()].filter(Boolean).join(" · ");
        word = "no pulsetrackd";
        break;
      case "reconnecting": {
        const s = Math.round((now - S.downSince) / 1000);
        title = "connection to the console server lost: reconnecting…";
        text = [`down for ${s} s`, lastData()].filter(Boolean).join(" · ");
        word = "reconnecting";
        break;
      }
      case "silent": {
        const s = Math.round((now - S.lastLinkAt) / 1000);
        title = `no news from the console server for ${s} s`;
        text = lastData();
        word = "no news";
        break;
      }
      default:
        title = S.stream === "open" ? "connected: waiting for pulsetrackd's status…" : "connecting to the console server…";
        text = "";
        word = "connecting";
    }
    const daemon = mode === "live" ? "true" : "false";
    if (banner.dataset.daemon !== daemon) banner.dataset.daemon = daemon;
    if (banner.dataset.link !== mode) banner.dataset.link = mode;
    if (pill.dataset.link !== mode) pill.dataset.link = mode;
    setText(banner.querySelector(".banner-title"), title);
    setText(banner.querySelector(".banner-text"), text);
    setText(pill.querySelector(".link-word"), word);
    document.body.classList.toggle("stale", mode !== "live");
  }

  // what the page still shows while not live (only if it ever had something)
  function lastData() {
    const had = S.healthSeen || sides.left.shown > 0 || sides.right.shown > 0 || disp.last !== null;
    return had ? "showing the last data, greyed" : "";
  }

  function tick() {
    updateLink();
    updateDisplacementStatus();
    const d = new Date();
    setText("clock", d.toLocaleTimeString("en-GB", { hour12: false }));
  }

  // ---------------------------------------------------------------------------------------------
  // event stream
  let es = null;
  let retryDelay = 1000;
  let retryTimer = 0;

  const handlers = {
    link: onLink,
    health: onHealth,
    image: onImage,
    features: onFeatures,
    roi: onRoi,
    deformation: onDeformation,
    spectrum: onSpectrum,
    field: onField,
    command: onCommandEvent,
  };

  function connect() {
    retryTimer = 0;
    if (leaving) return;
    es = new EventSource("/api/events");
    es.onopen = () => {
      S.stream = "open";
      S.everOpen = true;
      S.lastLinkAt = performance.now();   // grace period before "silent"
      retryDelay = 1000;
      updateLink();
    };
    es.onerror = () => {
      if (S.stream !== "reconnecting") S.downSince = performance.now();
      S.stream = "reconnecting";
      S.everOpen = true;   // from now on the banner says "reconnecting", not "connecting"
      updateLink();
      // CONNECTING: the browser retries by itself. CLOSED: it gave up (an HTTP error status such
      // as 401, or a response that is not an event stream): find out why, then retry ourselves.
      if (es.readyState === EventSource.CLOSED) {
        es.close();
        probeThenRetry();
      }
    };
    for (const [name, fn] of Object.entries(handlers)) {
      es.addEventListener(name, (ev) => {
        let data;
        try { data = JSON.parse(ev.data); } catch (_) { return; }   // ignore a malformed event
        if (data === null || typeof data !== "object") return;
        try { fn(data); } catch (err) { reportError(name, err); }
      });
    }
  }

  async function probeThenRetry() {
    // EventSource hides the status code: ask the same URL, abort once the headers are in.
    const ctl = new AbortController();
    try {
      const r = await fetch("/api/events", { signal: ctl.signal, cache: "no-store", credentials: "same-origin" });
      ctl.abort();
      if (r.status === 401 || (r.redirected && r.url.includes("/login.html"))) {
        toLogin();
        return;
      }
    } catch (_) { /* unreachable: retry below */ }
    if (!retryTimer) retryTimer = setTimeout(connect, retryDelay);
    retryDelay = Math.min(retryDelay * 2, 10000);
  }

  // A bug in one handler must not take the page down; keep it visible for whoever debugs.
  function reportError(where, err) {
    console.error(`pulsetrack console: ${where}:`, err);
  }

  function onLink(d) {
    S.linkSeen = true;
    S.daemon = d.daemon === true;
    S.dds = d.dds === true;
    S.linkText = typeof d.text === "string" ? d.text : "";
    S.lastLinkAt = performance.now();
    updateLink();
  }

  // ---------------------------------------------------------------------------------------------
  // health panel
  const badge = $("health-state");

  function onHealth(d) {
    const state = typeof d.state === "string" && d.state ? d.state : "unknown";
    if (!S.healthSeen) {
      S.healthSeen = true;
      $("health-text").classList.add("seen");   // "(last known)" applies from now on
    }
    if (badge.dataset.state !== state) badge.dataset.state = state;
    setText(badge.querySelector(".badge-word"), state);
    setText("health-text", typeof d.state_text === "string" && d.state_text ? d.state_text : state);

    setText("h-fps", num(d.fps) ? `${d.fps.toFixed(1)} fps` : "—");
    setText("h-frames", fmtInt(d.frames));
    setText("h-drops", fmtInt(d.drops));
    setText("h-deadline", fmtInt(d.deadline_misses));
    setText("h-unpaired", fmtInt(d.unpaired));
    setText("h-missing", fmtInt(d.missing_triggers));
    setText("h-trigger", str(d.trigger_state));
    setText("h-source", [d.source, d.source_state].filter((s) => typeof s === "string" && s).join(": ") || "—");
    setText("h-tracking", str(d.tracking_state));
    setText("h-recorder", str(d.recorder_state));
    setText("h-output", str(d.output_state));
    setText("h-clock", str(d.clock_state));
    setText("h-security", str(d.security_state));
    setText("h-faults", `source ${fmtInt(d.source_faults)} · recorder ${fmtInt(d.recorder_faults)}`);
    setText("h-commands", `${fmtInt(d.commands_accepted)} accepted · ${fmtInt(d.commands_refused)} refused`);

    const le = $("h-last-error");
    const hasError = typeof d.last_error === "string" && d.last_error !== "";
    setText(le, hasError ? d.last_error : "none");
    le.classList.toggle("has-error", hasError);

    const body = $("stage-body");
    const stages = Array.isArray(d.stages) ? d.stages : [];
    if (stages.length === 0) {
      body.replaceChildren(row(["no stage timings yet"], true));
    } else {
      // reuse rows when the stage list keeps its length (the usual case at 1 Hz)
      if (body.children.length !== stages.length || body.querySelector(".muted")) {
        body.replaceChildren(...stages.map(() => row(["", "", "", ""])));
      }
      stages.forEach((s, i) => {
        const cells = body.children[i].children;
        setText(cells[0], str(s && s.stage));
        setText(cells[1], fmtMs(s && s.p50_us));
        setText(cells[2], fmtMs(s && s.p99_us));
        setText(cells[3], fmtMs(s && s.max_us));
      });
    }

    if (num(d.image_width) && num(d.image_height) && d.image_width > 0 && d.image_height > 0 &&
        (d.image_width !== S.fullW || d.image_height !== S.fullH)) {
      S.fullW = d.image_width;
      S.fullH = d.image_height;
      for (const side of Object.values(sides)) setAspect(side);
      S.overlayDirty = true;
      validateRoiForm();
    }
  }

  function row(texts, muted) {
    const tr = document.createElement("tr");
    for (const t of texts) {
      const td = document.createElement("td");
      td.textContent = t;
      if (muted) { td.colSpan = 4; td.className = "muted"; }
      tr.append(td);
    }
    return tr;
  }

  // ---------------------------------------------------------------------------------------------
  // images
  function setAspect(side) {
    const w = S.fullW || side.natW;
    const h = S.fullH || side.natH;
    if (w > 0 && h > 0) side.view.style.setProperty("--aspect", String(w / h));
  }

  // the full-image size features and ROIs refer to (health; else the preview's own size)
  function fullSize(side) {
    if (S.fullW > 0 && S.fullH > 0) return [S.fullW, S.fullH];
    if (side.natW > 0 && side.natH > 0) return [side.natW, side.natH];
    return null;
  }

  function onImage(d) {
    const side = sides[d.side];
    if (!side || !num(d.seq)) return;
    if (d.seq > side.wanted) side.wanted = d.seq;
    side.pendingFrame = num(d.frame) ? d.frame : null;
    if (!document.hidden) loadImage(side);
  }

  // At most one load per side; seqs announced meanwhile are skipped but for the newest.
  // The JPEG is decoded off-screen first, so a failed load (404: gone already) never replaces the
  // picture with a broken one; assigning the same URL to the visible <img> then takes the decoded
  // image from the document's list of available images (HTML standard), with no second request.
  async function loadImage(side) {
    if (side.loading || side.wanted <= side.tried) return;
    side.loading = true;
    const seq = side.wanted;
    const frame = side.pendingFrame;
    side.tried = seq;
    const url = `/api/image/${side.side}?seq=${seq}`;
    try {
      if (await show(side, url)) {
        side.shown = seq;
        side.frame = frame;
        side.natW = side.img.naturalWidth;
        side.natH = side.img.naturalHeight;
        side.placeholder.hidden = true;
        setText(side.info, `frame ${frame ?? "?"} · ${side.natW}×${side.natH}`);
        if (!S.fullW) setAspect(side);
        S.overlayDirty = true;
      }
    } catch (err) {
      reportError("image", err);
    } finally {
      side.loading = false;
    }
    if (side.wanted > side.tried && !document.hidden) loadImage(side);
  }

  async function show(side, url) {
    const probe = new Image();
    probe.src = url;
    try {
      await probe.decode();
    } catch (_) {
      return false;   // 404 (gone) or not an image: wait for the next one
    }
    const previous = side.img.getAttribute("src");
    const ok = await new Promise((resolve) => {
      side.img.onload = () => resolve(true);
      side.img.onerror = () => resolve(false);
      side.img.src = url;
    });
    if (!ok && previous) side.img.src = previous;   // a browser that fetched again and lost it
    return ok;
  }

  document.addEventListener("visibilitychange", () => {
    if (!document.hidden) for (const side of Object.values(sides)) loadImage(side);
  });

  // ---------------------------------------------------------------------------------------------
  // features, ROI overlay
  const legend = $("feature-legend");
  const legendCounts = {};

  function buildLegend() {
    const svg = (shape, colour) => {
      if (shape === "cross") {
        return `<svg viewBox="0 0 14 14" aria-hidden="true"><path d="M3 3L11 11M11 3L3 11" stroke="${colour}" stroke-width="2.2" fill="none"/></svg>`;
      }
      const r = shape === "small" ? 3.5 : 5;
      return `<svg viewBox="0 0 14 14" aria-hidden="true"><circle cx="7" cy="7" r="${r}" stroke="${colour}" stroke-width="2" fill="none"/></svg>`;
    };
    const items = [
      ["ok", svg("circle", FEATURE_STATUS[0].colour), "ok"],
      ["occluded", svg("circle", FEATURE_STATUS[1].colour), "occluded"],
      ["lost", svg("small", FEATURE_STATUS[2].colour), "lost"],
      ["outlier", svg("cross", FEATURE_STATUS[3].colour), "outlier"],
    ];
    // Static markup (no data in it); counts are filled with textContent.
    legend.innerHTML =
      items.map(([key, icon, label]) =>
        `<span class="item">${icon}<span>${label}</span> <span class="count" data-key="${key}">0</span></span>`).join("") +
      `<span class="item outlier-detail muted" data-key="outlier-detail"></span>` +
      `<span class="item"><span class="roi-key" aria-hidden="true"></span>ROI</span>` +
      `<span class="item pending-key" hidden><span class="roi-key pending" aria-hidden="true"></span>new ROI</span>` +
      `<span class="item muted" data-key="frame"></span>`;
    for (const el of legend.querySelectorAll("[data-key]")) legendCounts[el.dataset.key] = el;
  }

  function onFeatures(d) {
    if (!Array.isArray(d.items)) return;
    S.features = d;
    if (!legendCounts.ok) buildLegend();
    const c = [0, 0, 0, 0, 0, 0];
    let other = 0;
    for (const it of d.items) {
      const st = Array.isArray(it) ? it[1] : -1;
      if (st >= 0 && st <= 5) c[st]++;
      else other++;
    }
    setText(legendCounts.ok, String(c[0]));
    setText(legendCounts.occluded, String(c[1]));
    setText(legendCounts.lost, String(c[2]));
    setText(legendCounts.outlier, String(c[3] + c[4] + c[5]));
    setText(legendCounts["outlier-detail"],
      c[3] + c[4] + c[5] > 0 ? `(epipolar ${c[3]} · surface ${c[4]} · triangulation ${c[5]})` : "");
    setText(legendCounts.frame, `features of frame ${num(d.frame) ? d.frame : "?"}` + (other ? ` · ${other} unknown status` : ""));
    S.overlayDirty = true;
  }

  function onRoi(d) {
    S.roi = {
      left: isRect(d.left) ? d.left : null,
      right: isRect(d.right) ? d.right : null,
      depth_tolerance_mm: num(d.depth_tolerance_mm) ? d.depth_tolerance_mm : null,
    };
    S.overlayDirty = true;
  }

  function drawOverlay(side) {
    const { ctx, w, h } = fitCanvas(side.overlay);
    ctx.clearRect(0, 0, w, h);
    const full = fullSize(side);
    if (!full) return;
    const sx = w / full[0];
    const sy = h / full[1];

    // features
    const f = S.features;
    if (f && side.shown > 0) {
      const ix = side.side === "left" ? 2 : 4;
      ctx.lineWidth = 2;
      for (const it of f.items) {
        if (!Array.isArray(it)) continue;
        const x = it[ix], y = it[ix + 1];
        if (!num(x) || !num(y)) continue;
        const st = FEATURE_STATUS[it[1]];
        if (!st) continue;
        const px = x * sx, py = y * sy;
        ctx.strokeStyle = st.colour;
        ctx.beginPath();
        if (st.shape === "cross") {
          ctx.moveTo(px - 4.5, py - 4.5); ctx.lineTo(px + 4.5, py + 4.5);
          ctx.moveTo(px + 4.5, py - 4.5); ctx.lineTo(px - 4.5, py + 4.5);
        } else {
          ctx.arc(px, py, st.shape === "small" ? 3 : 5, 0, 2 * Math.PI);
        }
        ctx.stroke();
      }
    }

    // ROI in force: solid; ROI being edited or dragged: dashed
    const roi = S.roi && S.roi[side.side];
    if (roi) rect(ctx, roi, sx, sy, ROI_COLOUR, false, "ROI");
    if (S.drag) {
      if (side.side === "left") rect(ctx, dragRect(S.drag), sx, sy, ROI_PENDING_COLOUR, true, "");
    } else if (S.pending) {
      const p = S.pending[side.side];
      if (p) rect(ctx, p, sx, sy, ROI_PENDING_COLOUR, true, side.side === "left" ? "new ROI" : "new ROI (derived)");
    }
  }

  function rect(ctx, r, sx, sy, colour, dashed, label) {
    const [x, y, w, h] = r;
    ctx.save();
    ctx.lineWidth = 2;
    ctx.strokeStyle = "rgba(0,0,0,0.6)";          // dark halo: visible on bright tissue and glints
    ctx.setLineDash(dashed ? [8, 5] : []);
    ctx.strokeRect(x * sx + 1, y * sy + 1, w * sx, h * sy);
    ctx.strokeStyle = colour;
    ctx.strokeRect(x * sx, y * sy, w * sx, h * sy);
    if (label) {
      ctx.font = "600 12px system-ui, sans-serif";
      ctx.textBaseline = "bottom";
      const tx = x * sx;
      const ty = y * sy > 16 ? y * sy - 3 : y * sy + h * sy + 15;
      ctx.fillStyle = "rgba(0,0,0,0.65)";
      ctx.fillRect(tx, ty - 14, ctx.measureText(label).width + 8, 16);
      ctx.fillStyle = colour;
      ctx.fillText(label, tx + 4, ty);
    }
    ctx.restore();
  }

  // ---------------------------------------------------------------------------------------------
  // ROI drawing on the left image (Pointer Events: mouse, pen and finger alike)
  const leftOverlay = sides.left.overlay;

  function toFullPx(ev) {
    const full = fullSize(sides.left);
    if (!full) return null;
    const r = leftOverlay.getBoundingClientRect();
    const x = ((ev.clientX - r.left) / r.width) * full[0];
    const y = ((ev.clientY - r.top) / r.height) * full[1];
    return { x: Math.min(Math.max(x, 0), full[0]), y: Math.min(Math.max(y, 0), full[1]), cx: ev.clientX, cy: ev.clientY };
  }

  function dragRect(d) {
    const x0 = Math.round(Math.min(d.x0, d.x1)), x1 = Math.round(Math.max(d.x0, d.x1));
    const y0 = Math.round(Math.min(d.y0, d.y1)), y1 = Math.round(Math.max(d.y0, d.y1));
    return [x0, y0, x1 - x0, y1 - y0];
  }

  leftOverlay.addEventListener("pointerdown", (ev) => {
    if (ev.pointerType === "mouse" && ev.button !== 0) return;
    const p = toFullPx(ev);
    if (!p) {
      setText("roi-hint", "wait for the first image before drawing a region of interest");
      return;
    }
    ev.preventDefault();
    leftOverlay.setPointerCapture(ev.pointerId);
    S.drag = { id: ev.pointerId, x0: p.x, y0: p.y, x1: p.x, y1: p.y, cx0: p.cx, cy0: p.cy, cx1: p.cx, cy1: p.cy };
    S.overlayDirty = true;
  });
  leftOverlay.addEventListener("pointermove", (ev) => {
    if (!S.drag || ev.pointerId !== S.drag.id) return;
    const p = toFullPx(ev);
    if (!p) return;
    Object.assign(S.drag, { x1: p.x, y1: p.y, cx1: p.cx, cy1: p.cy });
    S.overlayDirty = true;
  });
  leftOverlay.addEventListener("pointerup", (ev) => {
    if (!S.drag || ev.pointerId !== S.drag.id) return;
    const p = toFullPx(ev);
    if (p) Object.assign(S.drag, { x1: p.x, y1: p.y, cx1: p.cx, cy1: p.cy });
    const d = S.drag;
    S.drag = null;
    S.overlayDirty = true;
    const r = dragRect(d);
    const tiny = Math.abs(d.cx1 - d.cx0) < MIN_DRAG_CSS_PX || Math.abs(d.cy1 - d.cy0) < MIN_DRAG_CSS_PX;
    if (tiny || r[2] <= 0 || r[3] <= 0) return;   // a tap or a zero-size drag: ignored
    openRoiPanel(r);
  });
  leftOverlay.addEventListener("pointercancel", () => {
    S.drag = null;
    S.overlayDirty = true;
  });

  // ---------------------------------------------------------------------------------------------
  // ROI panel
  const roiPanel = $("roi-panel");
  const roiInputs = { x: $("roi-x"), y: $("roi-y"), w: $("roi-w"), h: $("roi-h"), tol: $("roi-tol") };
  const roiError = $("roi-error");
  let roiRightSeq = 0;
  let roiRightTimer = 0;
  let roiRequestId = null;   // request_id of the set_roi sent from this panel

  function openRoiPanel(r) {
    roiInputs.x.value = r[0];
    roiInputs.y.value = r[1];
    roiInputs.w.value = r[2];
    roiInputs.h.value = r[3];
    if (roiInputs.tol.value === "") roiInputs.tol.value = DEFAULT_TOLERANCE_MM;
    roiRequestId = null;
    roiPanel.hidden = false;
    setRoiError("");
    validateRoiForm();
  }

  function closeRoiPanel() {
    roiPanel.hidden = true;
    S.pending = null;
    roiRequestId = null;
    clearTimeout(roiRightTimer);
    roiRightSeq++;
    setRoiError("");
    legend.querySelector(".pending-key")?.setAttribute("hidden", "");
    S.overlayDirty = true;
  }

  function setRoiError(text) {
    setText(roiError, text);
  }

  // Read and check the form; returns {roi, tol} or {error, field}.
  function readRoiForm() {
    const vals = {};
    for (const k of ["x", "y", "w", "h"]) {
      const raw = roiInputs[k].value.trim();
      const v = Number(raw);
      if (raw === "" || !Number.isFinite(v)) return { error: `${k} is missing or not a number`, field: k };
      if (!Number.isInteger(v)) return { error: `${k} must be a whole number of pixels`, field: k };
      vals[k] = v;
    }
    const tolRaw = roiInputs.tol.value.trim();
    const tol = Number(tolRaw);
    if (vals.w <= 0) return { error: "w must be at least 1 px", field: "w" };
    if (vals.h <= 0) return { error: "h must be at least 1 px", field: "h" };
    if (vals.x < 0) return { error: "x must be 0 or more", field: "x" };
    if (vals.y < 0) return { error: "y must be 0 or more", field: "y" };
    const full = fullSize(sides.left);
    if (full) {
      const [W, H] = full;
      if (vals.x >= W) return { error: `x must be below the image width ${W}`, field: "x" };
      if (vals.y >= H) return { error: `y must be below the image height ${H}`, field: "y" };
      if (vals.x + vals.w > W) return { error: `x + w = ${vals.x + vals.w} exceeds the image width ${W}`, field: "w" };
      if (vals.y + vals.h > H) return { error: `y + h = ${vals.y + vals.h} exceeds the image height ${H}`, field: "h" };
    }
    if (tolRaw === "" || !Number.isFinite(tol) || tol <= 0) {
      return { error: "depth tolerance must be a number of mm above 0", field: "tol" };
    }
    return { roi: [vals.x, vals.y, vals.w, vals.h], tol };
  }

  // Live check while typing: mark the field, update the dashed rectangle and the derived right ROI.
  function validateRoiForm() {
    if (roiPanel.hidden) return null;
    const res = readRoiForm();
    for (const [k, el] of Object.entries(roiInputs)) {
      el.setAttribute("aria-invalid", res.field === k ? "true" : "false");
    }
    if (res.error) {
      setRoiError(res.error);
      S.pending = null;
      setText("roi-right", "—");
    } else {
      setRoiError("");
      const same = S.pending && S.pending.left.join() === res.roi.join() && S.pending.tol === res.tol;
      if (!same) {
        S.pending = { left: res.roi, right: null, tol: res.tol };
        setText("roi-right", "deriving…");
        clearTimeout(roiRightTimer);
        roiRightTimer = setTimeout(() => fetchRoiRight(res.roi, res.tol), 200);
      }
      legend.querySelector(".pending-key")?.removeAttribute("hidden");
    }
    S.overlayDirty = true;
    return res;
  }

  async function fetchRoiRight(roi, tol) {
    const my = ++roiRightSeq;
    const q = `roi_left=${roi.join(",")}&depth_tolerance_mm=${encodeURIComponent(tol)}`;
    const res = await api("GET", `/api/roi_right?${q}`);
    if (my !== roiRightSeq || !S.pending || S.pending.left.join() !== roi.join()) return;   // outdated
    if (res.ok && res.data && isRect(res.data.right)) {
      S.pending.right = res.data.right;
      const [x, y, w, h] = res.data.right;
      setText("roi-right", `x ${x}, y ${y}, ${w}×${h}`);
    } else {
      S.pending.right = null;
      setText("roi-right", `not derived: ${res.error || "no answer"}`);
    }
    S.overlayDirty = true;
  }

  for (const el of Object.values(roiInputs)) el.addEventListener("input", validateRoiForm);

  $("roi-form").addEventListener("submit", async (ev) => {
    ev.preventDefault();
    const res = validateRoiForm();
    if (!res || res.error) {
      roiInputs[res?.field || "x"].focus();
      return;   // refused client-side; the message is shown
    }
    const apply = $("apply-roi");
    apply.disabled = true;
    const body = { command: "set_roi", roi_left: res.roi, depth_tolerance_mm: res.tol };
    const out = await sendCommand(body, "Apply ROI");
    apply.disabled = false;
    if (out.ok) {
      roiRequestId = out.requestId;
      setRoiError("");
      // the outcome may have arrived before the reply
      const entry = logRows.get(out.requestId);
      if (entry && entry.li.dataset.state !== "sent") {
        applyCommandState(out.requestId, entry.li.dataset.state, entry.lastText || "");
      }
    } else {
      setRoiError(out.error);   // the server's 400/403/503 reason, in red beside the controls
    }
  });
  $("cancel-roi").addEventListener("click", closeRoiPanel);
  $("btn-roi-edit").addEventListener("click", () => {
    const full = fullSize(sides.left);
    let r = S.roi && S.roi.left;
    if (!r) r = full ? [Math.round(full[0] / 4), Math.round(full[1] / 4), Math.round(full[0] / 2), Math.round(full[1] / 2)] : [0, 0, 100, 100];
    openRoiPanel(r);
    roiInputs.x.focus();
  });

  // ---------------------------------------------------------------------------------------------
  // commands
  const statusLine = $("command-status");
  const commandLog = $("command-log");
  const logRows = new Map();     // request_id -> {li, label}
  let lastRequestId = null;
  const STATE_ICON = { sent: "\u2026", accepted: "\u2714", refused: "\u2716", unacknowledged: "?", error: "\u2716" };
  const COMMAND_LABEL = {
    start: "Start", stop: "Stop", redetect: "Re-detect", record_start: "Recorder on",
    record_stop: "Recorder off", set_roi: "Apply ROI",
  };

  function setStatus(state, text) {
    statusLine.dataset.state = state;
    setText(statusLine, `${STATE_ICON[state] || ""} ${text}`.trim());
  }

  function logLine(state, label, text, requestId) {
    let entry = requestId != null ? logRows.get(requestId) : null;
    if (!entry) {
      const li = document.createElement("li");
      li.innerHTML = '<span class="tm"></span><span class="st"></span><span class="txt"></span>';
      li.children[0].textContent = new Date().toLocaleTimeString("en-GB", { hour12: false });
      entry = { li, label };
      commandLog.prepend(li);
      if (requestId != null) logRows.set(requestId, entry);
      while (commandLog.children.length > 30) commandLog.lastElementChild.remove();
      // forget rows no longer shown
      if (logRows.size > 60) for (const k of [...logRows.keys()].slice(0, logRows.size - 60)) logRows.delete(k);
    }
    entry.li.dataset.state = state;
    entry.li.children[1].textContent = state;
    entry.li.children[2].textContent = `${entry.label}${requestId != null ? ` #${requestId}` : ""}${text ? `: ${text}` : ""}`;
    entry.li.title = entry.li.children[2].textContent;
    return entry;
  }

  async function sendCommand(body, label) {
    setStatus("sent", `${label}: sending…`);
    const res = await api("POST", "/api/command", body);
    if (res.ok) {
      const id = res.data && num(res.data.request_id) ? res.data.request_id : null;
      const state = (res.data && typeof res.data.state === "string" && res.data.state) || "sent";
      lastRequestId = id;
      // the command event may have overtaken the reply
      const known = id != null ? logRows.get(id) : null;
      if (known && known.li.dataset.state !== "sent") {
        known.label = label;
        applyCommandState(id, known.li.dataset.state, known.lastText || "");
      } else {
        logLine(state, label, "", id);
        setStatus(state, `${label}: ${state}, waiting for pulsetrackd…`);
      }
      return { ok: true, requestId: id };
    }
    if (res.status === 401) return { ok: false, error: res.error };
    logLine("error", label, res.error, null);
    setStatus("error", `${label} not sent: ${res.error}`);
    return { ok: false, error: res.error };
  }

  function applyCommandState(id, state, text) {
    const entry = logRows.get(id);
    const label = entry ? entry.label : "command";
    if (id === lastRequestId) {
      const words = { accepted: "accepted", refused: "refused", unacknowledged: "no answer from pulsetrackd", sent: "sent" };
      setStatus(state, `${label}: ${words[state] || state}${text ? ` (${text})` : ""}`);
    }
    if (id === roiRequestId) {
      if (state === "accepted") closeRoiPanel();
      else if (state === "refused" || state === "unacknowledged") {
        setRoiError(`ROI ${state}${text ? `: ${text}` : ""}`);
      }
    }
  }

  function onCommandEvent(d) {
    if (!num(d.request_id)) return;
    const state = typeof d.state === "string" ? d.state : "unknown";
    const text = typeof d.text === "string" ? d.text : "";
    const label = COMMAND_LABEL[d.command] || (typeof d.command === "string" ? d.command : "command");
    const entry = logLine(state, label, text, d.request_id);
    entry.lastText = text;
    // a command we have not sent (another console, pulsetrack ctl) newer than ours becomes "the last"
    if (lastRequestId === null || d.request_id > lastRequestId) lastRequestId = d.request_id;
    applyCommandState(d.request_id, state, text);
  }

  for (const btn of document.querySelectorAll("[data-command]")) {
    btn.addEventListener("click", async () => {
      btn.disabled = true;   // no double send on a double tap
      try {
        await sendCommand({ command: btn.dataset.command }, btn.textContent.trim());
      } finally {
        btn.disabled = false;
      }
    });
  }

  $("btn-logout").addEventListener("click", async () => {
    await api("POST", "/api/logout");
    toLogin();
  });

  // ---------------------------------------------------------------------------------------------
  // displacement plot (ring buffer, x = seconds relative to now on pulsetrackd's clock)
  const ring = {
    t: new Float64Array(RING_CAP), dx: new Float64Array(RING_CAP),
    dy: new Float64Array(RING_CAP), dz: new Float64Array(RING_CAP),
    start: 0, count: 0,
  };
  const disp = {
    plot: null, dirty: false, lastT: null, lastRecv: 0, frozenAt: null, last: null, lastDraw: 0,
  };

  function onDeformation(d) {
    if (!num(d.t) || !num(d.dx) || !num(d.dy) || !num(d.dz)) return;
    // the clock went back (daemon restarted, clock stepped): start afresh
    if (disp.lastT !== null && d.t < disp.lastT - 1) ring.count = 0;
    if (disp.lastT !== null && d.t <= disp.lastT && ring.count > 0) return;   // duplicate or reordered
    const i = (ring.start + ring.count) % RING_CAP;
    ring.t[i] = d.t; ring.dx[i] = d.dx; ring.dy[i] = d.dy; ring.dz[i] = d.dz;
    if (ring.count < RING_CAP) ring.count++;
    else ring.start = (ring.start + 1) % RING_CAP;
    while (ring.count > 0 && ring.t[ring.start] < d.t - KEEP_S) {
      ring.start = (ring.start + 1) % RING_CAP;
      ring.count--;
    }
    disp.lastT = d.t;
    disp.lastRecv = performance.now();
    disp.last = d;
    disp.dirty = true;
  }

  // "now" on pulsetrackd's clock: the newest sample's stamp plus the time since it arrived; frozen
  // while the link is not live so that the last data stays on screen.
  function displacementNow() {
    if (disp.lastT === null) return null;
    if (S.mode !== "live") {
      if (disp.frozenAt === null) disp.frozenAt = disp.lastT + (performance.now() - disp.lastRecv) / 1000;
      return disp.frozenAt;
    }
    disp.frozenAt = null;
    return disp.lastT + (performance.now() - disp.lastRecv) / 1000;
  }

  function updateDisplacementStatus() {
    const el = $("disp-status");
    if (disp.last === null) {
      el.className = "plot-status big";
      setText(el, "no displacement yet");
      return;
    }
    const d = disp.last;
    const quiet = (performance.now() - disp.lastRecv) / 1000;
    el.className = "plot-status";
    let text = num(d.ok) && num(d.total) ? `features ok ${d.ok} of ${d.total}` : "";
    if (S.mode === "live" && quiet > DISP_QUIET_S) {
      text = `no displacement for ${Math.round(quiet)} s (tracking stopped?)` + (text ? ` · last: ${text}` : "");
    }
    setText(el, text);
    const mag = Math.hypot(d.dx, d.dy, d.dz);
    setText("disp-now", `dx ${fmtMm(d.dx)} dy ${fmtMm(d.dy)} dz ${fmtMm(d.dz)} |d| ${fmtMm(mag)} mm`);
  }

  function makeAxis(label, fmt, size) {
    const axis = {
      stroke: AXIS_COLOUR,
      grid: { stroke: GRID_COLOUR, width: 1 },
      ticks: { stroke: GRID_COLOUR, width: 1 },
      font: "12px system-ui, sans-serif",
      labelFont: "12px system-ui, sans-serif",
      label,
      labelSize: 18,
      values: fmt,
    };
    if (size) axis.size = size;   // (an undefined key would override uPlot's default)
    return axis;
  }

  // Plot height follows the viewport: 1280x800 tablet 190 px, 1920x1080 screen 230 px.
  function plotHeight() {
    return Math.round(Math.max(190, Math.min(230, window.innerHeight * 0.22)));
  }

  function plotSize(el) {
    return { width: Math.max(200, Math.floor(el.clientWidth)), height: plotHeight() };
  }

  function createDisplacementPlot() {
    const el = $("plot-displacement");
    const opts = {
      ...plotSize(el),
      legend: { show: true, live: false },
      cursor: { drag: { x: false, y: false }, points: { show: false } },
      scales: {
        x: { time: false, range: [-WINDOW_S, 0] },
        y: {
          range: (u, min, max) => {
            if (min === null || max === null || !Number.isFinite(min)) return [-0.5, 0.5];
            const span = Math.max(max - min, 0.1);   // never zoom into sub-0.1 mm noise
            const mid = (max + min) / 2;
            return [mid - span * 0.6, mid + span * 0.6];
          },
        },
      },
      axes: [
        makeAxis("s (0 = now)", (u, vals) => vals.map((v) => `${v}`), 34),
        makeAxis("mm", (u, vals) => vals.map((v) => v.toFixed(2))),
      ],
      series: [{ label: "s" }, ...DISP_SERIES.map((s) => ({ ...s, points: { show: false }, value: (u, v) => fmtMm(v) }))],
    };
    disp.plot = new uPlot(opts, [[], [], [], [], []], el);
  }

  function redrawDisplacement() {
    const now = displacementNow();
    if (now === null || !disp.plot) return;
    // A gap in the samples (an outage, tracking stopped) is drawn as a gap, not bridged: a null
    // point between samples more than GAP_S apart (uPlot does not span nulls).
    const x = [], dx = [], dy = [], dz = [], m = [];
    for (let k = 0; k < ring.count; k++) {
      const i = (ring.start + k) % RING_CAP;
      if (k > 0 && ring.t[i] - ring.t[(i + RING_CAP - 1) % RING_CAP] > GAP_S) {
        x.push(ring.t[i] - now - 1e-3);
        dx.push(null); dy.push(null); dz.push(null); m.push(null);
      }
      x.push(ring.t[i] - now);
      dx.push(ring.dx[i]);
      dy.push(ring.dy[i]);
      dz.push(ring.dz[i]);
      m.push(Math.hypot(ring.dx[i], ring.dy[i], ring.dz[i]));
    }
    disp.plot.setData([x, dx, dy, dz, m]);
  }

  // ---------------------------------------------------------------------------------------------
  // spectrum plot
  const spec = { plot: null, data: null, peaks: [], dirty: false };

  function onSpectrum(d) {
    const status = $("spectrum-status");
    const list = $("spectrum-peaks");
    if (typeof d.error === "string") {
      status.className = "plot-status big error";
      setText(status, d.error);
      spec.data = [[], []];
      spec.peaks = [];
      list.replaceChildren();
      setText("spectrum-window", "");
      spec.dirty = true;
      return;
    }
    const f = Array.isArray(d.frequency_hz) ? d.frequency_hz : [];
    const a = Array.isArray(d.amplitude_mm) ? d.amplitude_mm : [];
    const x = [], y = [];
    for (let i = 0; i < Math.min(f.length, a.length); i++) {
      if (num(f[i]) && f[i] >= 0 && f[i] <= SPECTRUM_MAX_HZ) {
        x.push(f[i]);
        y.push(num(a[i]) ? a[i] : null);
      }
    }
    spec.data = [x, y];
    spec.peaks = (Array.isArray(d.peaks) ? d.peaks : [])
      .filter((p) => p && num(p.frequency_hz) && num(p.amplitude_mm))
      .sort((p, q) => p.frequency_hz - q.frequency_hz);
    spec.dirty = true;

    status.className = "plot-status";
    setText(status, x.length ? "" : "empty spectrum");
    setText("spectrum-window", num(d.window_s) ? `window ${Math.round(d.window_s)} s` : "");
    list.replaceChildren(...spec.peaks.map((p) => {
      const li = document.createElement("li");
      const name = document.createElement("span");
      name.className = "pk-name";
      name.textContent = typeof p.name === "string" && p.name ? p.name : "peak";
      const vals = document.createElement("span");
      vals.textContent = `${p.frequency_hz.toFixed(2)} Hz (${(p.frequency_hz * 60).toFixed(0)} /min)  ${p.amplitude_mm.toFixed(2)} mm`;
      li.append(name, vals);
      return li;
    }));
    if (spec.peaks.length === 0 && x.length) {
      const li = document.createElement("li");
      li.className = "muted";
      li.textContent = "no named peak";
      list.append(li);
    }
  }

  function peakName(p) {
    return typeof p.name === "string" && p.name ? p.name : "peak";
  }

  function peakValues(p) {
    return `${p.frequency_hz.toFixed(2)} Hz, ${p.amplitude_mm.toFixed(2)} mm`;
  }

  // Named peaks: a marker on the curve and a label "breathing 0.20 Hz, 0.31 mm" (two lines when the
  // plot is narrow). Each label takes the free spot nearest its marker (markers, other labels, the
  // peaks' spikes and the noise floor are obstacles), with a leader line when it had to move away.
  function drawPeaks(u) {
    const ctx = u.ctx;
    const dpr = window.devicePixelRatio || 1;
    const left = u.bbox.left, right = u.bbox.left + u.bbox.width;
    const top = u.bbox.top, bottom = u.bbox.top + u.bbox.height;
    const lineH = 15 * dpr, gap = 4 * dpr;
    ctx.save();
    ctx.font = `600 ${Math.round(12 * dpr)}px system-ui, sans-serif`;
    ctx.textAlign = "left";        // uPlot leaves its axis alignment behind
    ctx.textBaseline = "bottom";
    // Only the named peaks are labelled on the plot (the list below has every peak).
    const shown = spec.peaks.filter((p) => p.frequency_hz <= SPECTRUM_MAX_HZ && peakName(p) !== "peak")
      .map((p) => ({ p, cx: u.valToPos(p.frequency_hz, "x", true), cy: u.valToPos(p.amplitude_mm, "y", true) }));
    const placed = [{ x0: left, x1: right, y0: bottom - 10 * dpr, y1: bottom }];   // noise floor
    const free = (box) => placed.every((o) =>
      box.x1 + gap <= o.x0 || box.x0 - gap >= o.x1 || box.y1 <= o.y0 || box.y0 >= o.y1);

    ctx.fillStyle = "#f0b429";
    for (const { cx, cy } of shown) {
      // a downward triangle just above the peak
      ctx.beginPath();
      ctx.moveTo(cx, cy - 2 * dpr);
      ctx.lineTo(cx - 5 * dpr, cy - 10 * dpr);
      ctx.lineTo(cx + 5 * dpr, cy - 10 * dpr);
      ctx.closePath();
      ctx.fill();
      placed.push({ x0: cx - 6 * dpr, x1: cx + 6 * dpr, y0: cy - 11 * dpr, y1: bottom });   // marker + spike
    }

    shown.sort((a, b) => b.p.amplitude_mm - a.p.amplitude_mm);   // the largest peak chooses first
    for (const { p, cx, cy } of shown) {
      let lines = [`${peakName(p)} ${peakValues(p)}`];
      if (ctx.measureText(lines[0]).width > (right - left) * 0.7) lines = [peakName(p), peakValues(p)];
      const tw = Math.max(...lines.map((l) => ctx.measureText(l).width));
      const th = lineH * lines.length;
      const clampX = (x) => Math.max(left + 2 * dpr, Math.min(x, right - tw - 2 * dpr));
      const anchorY = cy - 12 * dpr;   // label bottom right above the marker
      let best = null, bestCost = Infinity;
      let leastBad = null, leastOverlap = Infinity;   // if nothing is free: the least covered spot
      const overlap = (box) => placed.reduce((sum, o) =>
        sum + Math.max(0, Math.min(box.x1, o.x1) - Math.max(box.x0, o.x0)) *
              Math.max(0, Math.min(box.y1, o.y1) - Math.max(box.y0, o.y0)), 0);
      const stepY = lineH / 2, stepX = 12 * dpr;
      for (let y1 = Math.min(anchorY, bottom - 12 * dpr); y1 - th >= top; y1 -= stepY) {
        for (let x0 = left + 2 * dpr; x0 <= right - tw; x0 += stepX) {
          for (const x of [x0, clampX(cx - tw / 2)]) {
            const box = { x0: x, x1: x + tw, y0: y1 - th, y1 };
            // distance from the marker to the nearest point of the box; going down costs more
            const dx = Math.max(box.x0 - cx, 0, cx - box.x1);
            const dy = Math.abs(anchorY - y1);
            const cost = dx + dy * (y1 > anchorY ? 3 : 1);
            if (cost < bestCost && free(box)) { best = box; bestCost = cost; }
            if (!best) {
              const ov = overlap(box) + cost;   // cost breaks ties between equally covered spots
              if (ov < leastOverlap) { leastBad = box; leastOverlap = ov; }
            }
          }
        }
      }
      if (!best && leastBad) best = leastBad;
      if (!best) {   // the plot is smaller than the label: right above the marker
        const y1 = Math.max(top + th, anchorY);
        best = { x0: clampX(cx - tw / 2), y0: y1 - th, y1 };
        best.x1 = best.x0 + tw;
      }
      const far = Math.max(best.x0 - cx, 0, cx - best.x1) + Math.abs(anchorY - best.y1);
      if (far > 8 * dpr) {
        // leader line from the marker to the label's nearest edge
        const lx = Math.max(best.x0, Math.min(cx, best.x1));
        const ly = cy - 10 * dpr > best.y1 ? best.y1 : best.y0 > cy ? best.y0 : (best.y0 + best.y1) / 2;
        ctx.strokeStyle = "rgba(244,210,122,0.6)";
        ctx.lineWidth = 1 * dpr;
        ctx.beginPath();
        ctx.moveTo(cx, cy - 10 * dpr);
        ctx.lineTo(lx, ly);
        ctx.stroke();
      }
      ctx.fillStyle = "rgba(12,15,20,0.8)";
      ctx.fillRect(best.x0 - 3 * dpr, best.y0 + 1 * dpr, tw + 6 * dpr, th);
      ctx.fillStyle = "#f4d27a";
      lines.forEach((l, i) => ctx.fillText(l, best.x0, best.y1 - (lines.length - 1 - i) * lineH));
      placed.push(best);
    }
    ctx.restore();
  }

  function createSpectrumPlot() {
    const el = $("plot-spectrum");
    const opts = {
      ...plotSize(el),
      legend: { show: false },
      cursor: { drag: { x: false, y: false } },
      scales: {
        x: { time: false, range: [0, SPECTRUM_MAX_HZ] },
        y: {
          // headroom above the highest peak for the labels, more with more peaks
          range: (u, min, max) =>
            [0, Math.max(num(max) ? max * (1.3 + 0.15 * Math.min(spec.peaks.length, 4)) : 0.1, 0.05)],
        },
      },
      axes: [
        makeAxis("Hz", (u, vals) => vals.map((v) => v.toFixed(1)), 34),
        makeAxis("mm", (u, vals) => vals.map((v) => v.toFixed(2))),
      ],
      series: [
        { label: "Hz" },
        { label: "amplitude", stroke: "#5fb3e6", width: 1.6, fill: "rgba(95,179,230,0.12)", points: { show: false } },
      ],
      hooks: { draw: [drawPeaks] },
    };
    spec.plot = new uPlot(opts, [[], []], el);
  }

  // ---------------------------------------------------------------------------------------------
  // dense field heat map (viridis computed here)
  const field = { data: null, dirty: false };
  const fieldCanvas = $("field-map");

  // viridis, polynomial fit (Matt Zucker, CC0); t in [0, 1] -> [r, g, b] 0..255
  function viridis(t) {
    const c = [
      [0.2777273272234177, 0.005407344544966578, 0.3340998053353061],
      [0.1050930431085774, 1.404613529898575, 1.384590162594685],
      [-0.3308618287255563, 0.214847559468213, 0.09509516302823659],
      [-4.634230498983486, -5.799100973351585, -19.33244095627987],
      [6.228269936347081, 14.17993336680509, 56.69055260068105],
      [4.776384997670288, -13.74514537774601, -65.35303263337234],
      [-5.435455855934631, 4.645852612178535, 26.3124352495832],
    ];
    const out = [0, 0, 0];
    for (let ch = 0; ch < 3; ch++) {
      let v = c[6][ch];
      for (let k = 5; k >= 0; k--) v = c[k][ch] + t * v;
      out[ch] = Math.round(Math.min(1, Math.max(0, v)) * 255);
    }
    return out;
  }
  const VIRIDIS = Array.from({ length: 256 }, (_, i) => viridis(i / 255));

  function onField(d) {
    const rows = d.rows, cols = d.cols;
    if (!Number.isInteger(rows) || !Number.isInteger(cols) || rows <= 0 || cols <= 0) return;
    const m = Array.isArray(d.magnitude_mm) ? d.magnitude_mm : null;
    if (!m || m.length !== rows * cols) return;
    let max = num(d.max_mm) && d.max_mm > 0 ? d.max_mm : 0;
    let known = 0;
    for (const v of m) {
      if (num(v)) {
        known++;
        if (!(num(d.max_mm) && d.max_mm > 0) && v > max) max = v;
      }
    }
    field.data = { rows, cols, m, max: max > 0 ? max : 1e-3, known };
    field.dirty = true;
    fieldCanvas.hidden = false;
    const status = $("field-status");
    status.className = "plot-status";
    setText(status, known < rows * cols ? `grey: unknown (${rows * cols - known} of ${rows * cols} points)` : "");
    setText("field-info", `${cols}×${rows} grid · max ${fmtMm(field.data.max)} mm`);
  }

  // the heat map as tall as the uPlot plots beside it (plot area + legend)
  function setFieldHeight() {
    $("field-wrap").style.height = `${plotHeight() + 24}px`;
    field.dirty = true;
  }

  function drawField() {
    const f = field.data;
    if (!f) return;
    const { ctx, w, h } = fitCanvas(fieldCanvas);
    ctx.clearRect(0, 0, w, h);
    // colour bar on the right, the map fitted (square cells) in the rest
    const barW = 14, barLabelW = 52, pad = 6;
    const mapW = w - barW - barLabelW - pad * 2;
    const mapH = h - pad * 2;
    const cell = Math.max(0.5, Math.min(mapW / f.cols, mapH / f.rows));
    const gw = cell * f.cols, gh = cell * f.rows;
    const gx = pad + (mapW - gw) / 2, gy = pad + (mapH - gh) / 2;

    const off = document.createElement("canvas");
    off.width = f.cols;
    off.height = f.rows;
    const octx = off.getContext("2d");
    const img = octx.createImageData(f.cols, f.rows);
    for (let i = 0; i < f.m.length; i++) {
      const v = f.m[i];
      const o = i * 4;
      if (num(v)) {
        const c = VIRIDIS[Math.max(0, Math.min(255, Math.round((v / f.max) * 255)))];
        img.data[o] = c[0]; img.data[o + 1] = c[1]; img.data[o + 2] = c[2]; img.data[o + 3] = 255;
      } else {
        img.data[o] = 58; img.data[o + 1] = 63; img.data[o + 2] = 72; img.data[o + 3] = 255;   // unknown
      }
    }
    octx.putImageData(img, 0, 0);
    ctx.imageSmoothingEnabled = false;   // honest cells, no invented values between grid points
    ctx.drawImage(off, gx, gy, gw, gh);
    ctx.strokeStyle = "#2a323e";
    ctx.lineWidth = 1;
    ctx.strokeRect(gx - 0.5, gy - 0.5, gw + 1, gh + 1);

    // colour bar, 0 at the bottom
    const bx = w - barLabelW - barW - pad, by = pad + 18, bh = h - pad * 2 - 26;
    const grad = ctx.createLinearGradient(0, by + bh, 0, by);
    for (let k = 0; k <= 10; k++) {
      const c = VIRIDIS[Math.round((k / 10) * 255)];
      grad.addColorStop(k / 10, `rgb(${c[0]},${c[1]},${c[2]})`);
    }
    ctx.fillStyle = grad;
    ctx.fillRect(bx, by, barW, bh);
    ctx.strokeRect(bx - 0.5, by - 0.5, barW + 1, bh + 1);
    ctx.fillStyle = AXIS_COLOUR;
    ctx.font = "12px system-ui, sans-serif";
    ctx.textAlign = "left";
    ctx.textBaseline = "middle";
    const digits = f.max < 0.1 ? 3 : 2;
    for (const frac of [0, 0.25, 0.5, 0.75, 1]) {
      const y = by + bh - frac * bh;
      ctx.fillRect(bx + barW, Math.round(y), 4, 1);
      ctx.fillText((f.max * frac).toFixed(digits), bx + barW + 6, y);
    }
    ctx.textBaseline = "bottom";
    ctx.textAlign = "center";
    ctx.fillText("mm", bx + barW / 2 + 8, by - 6);
  }

  // ---------------------------------------------------------------------------------------------
  // render loop: overlays when something changed, plots at most every REDRAW_MS
  let lastPlotDraw = 0;
  function frame(ts) {
    try {
      if (S.overlayDirty) {
        S.overlayDirty = false;
        drawOverlay(sides.left);
        drawOverlay(sides.right);
      }
      if (ts - lastPlotDraw >= REDRAW_MS) {
        lastPlotDraw = ts;
        // the displacement plot scrolls while live, so it redraws even without new samples
        if (disp.plot && (disp.dirty || (S.mode === "live" && disp.lastT !== null))) {
          disp.dirty = false;
          redrawDisplacement();
        }
        if (spec.plot && spec.dirty) {
          spec.dirty = false;
          spec.plot.setData(spec.data);
        }
        if (field.dirty) {
          field.dirty = false;
          drawField();
        }
      }
    } catch (err) {
      reportError("render", err);
    }
    requestAnimationFrame(frame);
  }

  // who is logged in (GET /api/whoami: {"user", "role"}); optional, nothing shown without it
  async function showWhoAmI() {
    const res = await api("GET", "/api/whoami");
    if (!res.ok || !res.data || typeof res.data.user !== "string") return;
    const el = $("whoami");
    el.textContent = res.data.user;
    if (typeof res.data.role === "string" && res.data.role) {
      const role = document.createElement("span");
      role.className = "role";
      role.textContent = res.data.role;
      el.append(" · ", role);
    }
  }

  // ---------------------------------------------------------------------------------------------
  // start
  function init() {
    buildLegend();
    setText(legendCounts.frame, "no features yet");
    if (typeof uPlot === "function") {
      createDisplacementPlot();
      createSpectrumPlot();
    } else {
      setText("disp-status", "plot library (vendor/uplot) did not load");
      setText("spectrum-status", "plot library (vendor/uplot) did not load");
    }
    $("spectrum-status").className = "plot-status big";
    setText("spectrum-status", "no spectrum yet (it needs about 20 s of displacement)");

    const ro = new ResizeObserver((entries) => {
      for (const e of entries) {
        const t = e.target;
        if (t === sides.left.view || t === sides.right.view) S.overlayDirty = true;
        else if (t.id === "plot-displacement" && disp.plot) disp.plot.setSize(plotSize(t));
        else if (t.id === "plot-spectrum" && spec.plot) spec.plot.setSize(plotSize(t));
        else if (t.id === "field-wrap") field.dirty = true;
      }
    });
    for (const el of [sides.left.view, sides.right.view, $("plot-displacement"), $("plot-spectrum"), $("field-wrap")]) ro.observe(el);
    window.addEventListener("resize", () => {
      if (disp.plot) disp.plot.setSize(plotSize($("plot-displacement")));
      if (spec.plot) spec.plot.setSize(plotSize($("plot-spectrum")));
      setFieldHeight();
    });
    setFieldHeight();

    showWhoAmI();
    tick();
    setInterval(tick, 1000);
    requestAnimationFrame(frame);
    connect();
  }

  init();
})();
