// hdmap dashboard page: MapLibre map of the landmarks, kept live by server-sent events.
// Everything shown comes from the dashboard server (/events, /api/history/<id>); text from
// the bus (service names, ...) is only ever set as textContent, never parsed as HTML.
// window.hdmap exposes the page's state (the map, the landmarks by id) for inspection.
(function () {
  "use strict";

  const COLORS = {
    candidate: "#9e9e9e",
    located: "#1e88e5",
    confirmed: "#2e7d32",
    doubtful: "#ef6c00",
    retired: "#6d4c41",
  };
  const STATUS_COLOR = ["match", ["get", "status"]];
  for (const [k, v] of Object.entries(COLORS)) STATUS_COLOR.push(k, v);
  STATUS_COLOR.push("#000000");
  const EMPTY = { type: "FeatureCollection", features: [] };

  const state = {
    byId: new Map(), // landmark id -> its features (point, ellipse, arrow)
    counts: {},
    stats: null,
    connected: false,
    resets: 0,
    deltas: 0,
    renders: 0, // setData calls
    fitted: false,
    selected: null,
    ready: false, // style loaded, sources and layers added
    flushTimer: null,
  };
  window.hdmap = state;

  const map = new maplibregl.Map({
    container: "map",
    style: "/static/style.json",
    center: [0, 0],
    zoom: 1,
    attributionControl: false,
    maxPitch: 0,
  });
  state.map = map;
  state.fit = () => fitLandmarks();
  map.addControl(new maplibregl.NavigationControl(), "top-left");
  map.addControl(new maplibregl.ScaleControl({ unit: "metric" }), "bottom-left");

  // -- small DOM helpers ---------------------------------------------------------------------

  function el(tag, attrs, ...children) {
    const e = document.createElement(tag);
    for (const [k, v] of Object.entries(attrs || {})) {
      if (k === "class") e.className = v;
      else if (k === "style") e.style.cssText = v;
      else e.setAttribute(k, v);
    }
    for (const c of children) e.append(c instanceof Node ? c : document.createTextNode(String(c)));
    return e;
  }

  function fmt(v, digits) {
    if (v === null || v === undefined) return "–";
    if (typeof v !== "number") return String(v);
    return digits === undefined ? String(v) : v.toFixed(digits);
  }

  function time(t) {
    if (!t) return "–";
    return new Date(t * 1000).toLocaleTimeString([], { hour12: false });
  }

  // -- map layers ------------------------------------------------------------------------------

  map.on("load", () => {
    map.addSource("tiles", { type: "geojson", data: EMPTY });
    map.addSource("landmarks", { type: "geojson", data: EMPTY });
    map.addLayer({
      id: "tiles",
      type: "line",
      source: "tiles",
      paint: { "line-color": "#b0bec5", "line-width": 1, "line-dasharray": [3, 2] },
    });
    map.addLayer({
      id: "lm-ellipse-fill",
      type: "fill",
      source: "landmarks",
      filter: ["==", ["get", "kind"], "ellipse"],
      // candidates' ellipses are wide (few passes): fainter, so that they do not hide the rest
      paint: { "fill-color": STATUS_COLOR, "fill-opacity": ["match", ["get", "status"], "candidate", 0.07, 0.2] },
    });
    map.addLayer({
      id: "lm-ellipse-line",
      type: "line",
      source: "landmarks",
      filter: ["==", ["get", "kind"], "ellipse"],
      paint: { "line-color": STATUS_COLOR, "line-width": 1, "line-opacity": 0.8 },
    });
    map.addLayer({
      id: "lm-arrow",
      type: "line",
      source: "landmarks",
      filter: ["==", ["get", "kind"], "arrow"],
      layout: { "line-cap": "round" },
      paint: { "line-color": STATUS_COLOR, "line-width": 2 },
    });
    map.addLayer({
      id: "lm-selected",
      type: "circle",
      source: "landmarks",
      filter: ["==", ["get", "id"], ""],
      paint: { "circle-radius": 16, "circle-color": "rgba(0,0,0,0)", "circle-stroke-color": "#d50000", "circle-stroke-width": 3 },
    });
    map.addLayer({
      id: "lm-point",
      type: "circle",
      source: "landmarks",
      filter: ["==", ["get", "kind"], "point"],
      paint: {
        "circle-color": STATUS_COLOR,
        "circle-radius": ["interpolate", ["linear"], ["get", "passes"], 0, 3, 2, 4.5, 10, 7, 40, 11, 200, 15],
        "circle-stroke-color": "#ffffff",
        "circle-stroke-width": 1.5,
      },
    });
    // passes as a label: images drawn on demand (styleimagemissing), no glyphs needed
    map.addLayer({
      id: "lm-label",
      type: "symbol",
      source: "landmarks",
      filter: ["==", ["get", "kind"], "point"],
      layout: {
        "icon-image": ["concat", "passes-", ["to-string", ["get", "passes"]]],
        "icon-anchor": "left",
        "icon-offset": [9, 0],
        "icon-allow-overlap": false,
      },
    });
    map.on("click", (e) => {
      const id = landmarkAt(e.point);
      if (id !== null) select(id);
    });
    map.on("mousemove", (e) => {
      const hit = map.queryRenderedFeatures(box(e.point, 6), { layers: ["lm-point"] }).length > 0;
      map.getCanvas().style.cursor = hit ? "pointer" : "";
    });
    state.ready = true;
    flush();
    connect();
  });

  map.on("styleimagemissing", (e) => {
    if (!e.id.startsWith("passes-") || map.hasImage(e.id)) return;
    const text = e.id.slice("passes-".length);
    const r = window.devicePixelRatio || 1;
    const font = `600 ${11 * r}px system-ui, sans-serif`;
    const c = document.createElement("canvas");
    let ctx = c.getContext("2d");
    ctx.font = font;
    c.width = Math.ceil(ctx.measureText(text).width + 8 * r);
    c.height = Math.ceil(15 * r);
    ctx = c.getContext("2d");
    ctx.fillStyle = "rgba(255,255,255,0.85)";
    ctx.fillRect(0, 0, c.width, c.height);
    ctx.font = font;
    ctx.fillStyle = "#263238";
    ctx.textBaseline = "middle";
    ctx.fillText(text, 4 * r, c.height / 2);
    map.addImage(e.id, ctx.getImageData(0, 0, c.width, c.height), { pixelRatio: r });
  });

  function box(p, r) {
    return [
      [p.x - r, p.y - r],
      [p.x + r, p.y + r],
    ];
  }

  // The landmark a click means: the nearest point within 6 px, else the smallest 95 %
  // ellipse under the pointer (ellipses overlap; a point is what one aims at).
  function landmarkAt(p) {
    let best = null;
    let bestD = Infinity;
    for (const f of map.queryRenderedFeatures(box(p, 6), { layers: ["lm-point"] })) {
      const q = map.project(f.geometry.coordinates);
      const d = Math.hypot(q.x - p.x, q.y - p.y);
      if (d < bestD) [best, bestD] = [f.properties.id, d];
    }
    if (best !== null) return best;
    let bestArea = Infinity;
    for (const f of map.queryRenderedFeatures(p, { layers: ["lm-ellipse-fill"] })) {
      const fs = state.byId.get(f.properties.id);
      if (!fs) continue;
      const area = fs[0].properties.ellipse_major_m * fs[0].properties.ellipse_minor_m;
      if (area < bestArea) [best, bestArea] = [f.properties.id, area];
    }
    return best;
  }

  function allFeatures() {
    const out = [];
    for (const fs of state.byId.values()) out.push(...fs);
    return out;
  }

  function schedule() {
    if (state.flushTimer === null) state.flushTimer = setTimeout(flush, 100);
  }

  function flush() {
    state.flushTimer = null;
    if (!state.ready) return;
    map.getSource("landmarks").setData({ type: "FeatureCollection", features: allFeatures() });
    state.renders += 1;
    renderLegend();
    if (!state.fitted && state.byId.size > 0) fitLandmarks();
  }

  function fitLandmarks() {
    const b = new maplibregl.LngLatBounds();
    for (const fs of state.byId.values()) b.extend(fs[0].geometry.coordinates);
    map.fitBounds(b, { padding: 60, maxZoom: 18, duration: 0 });
    state.fitted = true;
  }

  function setTiles(d) {
    if (!state.ready) return;
    map.getSource("tiles").setData(d.tiles || EMPTY);
    if (!state.fitted && state.byId.size === 0 && d.bounds) {
      map.fitBounds(d.bounds, { padding: 20, duration: 0 });
    }
  }

  function upsert(features) {
    const fresh = new Map();
    for (const f of features) {
      const id = f.properties.id;
      if (!fresh.has(id)) fresh.set(id, []);
      fresh.get(id).push(f);
    }
    for (const [id, fs] of fresh) {
      fs.sort((a, b) => (a.properties.kind === "point" ? -1 : b.properties.kind === "point" ? 1 : 0));
      state.byId.set(id, fs);
    }
    return fresh;
  }

  // -- live updates ----------------------------------------------------------------------------

  function connect() {
    const es = new EventSource("/events");
    state.source = es;
    es.onopen = () => setConnected(true);
    es.onerror = () => setConnected(false); // EventSource reconnects by itself
    es.addEventListener("reset", (e) => {
      const d = JSON.parse(e.data);
      state.resets += 1;
      state.byId.clear();
      upsert(d.landmarks.features);
      state.counts = d.counts;
      setTiles(d);
      setStats(d.stats);
      schedule();
      if (state.selected) select(state.selected);
      document.getElementById("updated").textContent = "connected " + time(d.at);
    });
    es.addEventListener("delta", (e) => {
      const d = JSON.parse(e.data);
      state.deltas += 1;
      for (const id of d.removed) state.byId.delete(id);
      const fresh = upsert(d.upserts);
      state.counts = d.counts;
      schedule();
      if (state.selected && (fresh.has(state.selected) || d.removed.includes(state.selected))) {
        select(state.selected);
      }
      setUpdated(d.at);
    });
    es.addEventListener("tiles", (e) => setTiles(JSON.parse(e.data)));
    es.addEventListener("stats", (e) => setStats(JSON.parse(e.data)));
  }

  function setConnected(on) {
    state.connected = on;
    const c = document.getElementById("conn");
    c.className = "conn " + (on ? "on" : "off");
    c.textContent = on ? "live" : "reconnecting";
  }

  function setUpdated(t) {
    document.getElementById("updated").textContent = "last change " + time(t);
  }

  function renderLegend() {
    const legend = document.getElementById("legend");
    legend.replaceChildren();
    let total = 0;
    for (const [status, color] of Object.entries(COLORS)) {
      const n = (state.counts && state.counts[status]) || 0;
      total += n;
      legend.append(el("span", { class: "swatch", style: `background:${color}` }), `${status} ${n}`);
    }
    legend.prepend(`${total} landmarks:`);
  }

  // -- service health ----------------------------------------------------------------------------

  function setStats(s) {
    if (!s) return;
    state.stats = s;
    const body = document.querySelector("#stats tbody");
    body.replaceChildren();
    for (const r of s.services || []) {
      const warn = r.gaps_open > 0 || r.txn_failing > 0 || r.backlog > 100;
      const title = `${r.instance} region ${r.region}, up ${fmt(r.uptime_s, 0)} s, ` +
        `cpu ${fmt(r.cpu_s, 1)} s, rss ${fmt(r.rss_mb, 0)} MB` +
        (r.top_rejections.length ? "\nrejected: " + r.top_rejections.map((x) => `${x[0]} ${x[1]}`).join(", ") : "");
      body.append(
        el(
          "tr",
          { class: warn ? "warn" : "", title },
          el("td", {}, r.service),
          el("td", {}, fmt(r.backlog)),
          el("td", {}, fmt(r.lag_entries)),
          el("td", {}, `${fmt(r.accepted)} ${r.accepted_unit}`),
          el("td", {}, fmt(r.rejected)),
          el("td", {}, fmt(r.rate_per_s, 1)),
        ),
      );
    }
    if (!(s.services || []).length) {
      body.append(el("tr", {}, el("td", { colspan: "6" }, "no live services")));
    }
    const err = document.getElementById("stats-error");
    err.hidden = !s.error;
    err.textContent = s.error || "";
    const c = s.map_client;
    if (c) {
      document.getElementById("client").textContent =
        `map: ${c.tiles_fetched}/${c.tiles} tiles, ${c.snapshots} snapshots, ` +
        `${c.deltas_applied} deltas, ${c.gaps} gaps; stats ${time(s.updated_at)}`;
    }
  }

  // -- a landmark's history ------------------------------------------------------------------

  function select(id) {
    state.selected = id;
    if (state.ready) map.setFilter("lm-selected", ["all", ["==", ["get", "kind"], "point"], ["==", ["get", "id"], id]]);
    document.getElementById("close-landmark").hidden = false;
    document.getElementById("landmark-hint").hidden = true;
    fetch(`/api/history/${encodeURIComponent(id)}`)
      .then((r) => r.json())
      .then((h) => {
        if (state.selected === id) renderLandmark(id, h.entries || []);
      })
      .catch(() => {});
  }

  function deselect() {
    state.selected = null;
    if (state.ready) map.setFilter("lm-selected", ["==", ["get", "id"], ""]);
    document.getElementById("landmark-body").replaceChildren();
    document.getElementById("close-landmark").hidden = true;
    document.getElementById("landmark-hint").hidden = false;
  }
  document.getElementById("close-landmark").addEventListener("click", deselect);

  function renderLandmark(id, entries) {
    const body = document.getElementById("landmark-body");
    const fs = state.byId.get(id);
    const p = fs ? fs[0].properties : null;
    const rows = [];
    if (p) {
      const add = (k, v) => rows.push(el("tr", {}, el("td", {}, k), el("td", {}, v)));
      add("id", p.id);
      add("status", `${p.status}` + (p.p_exist ? ` (p_exist ${fmt(p.p_exist, 2)})` : ""));
      add("sign class", p.sign_class);
      add("passes / rays", `${p.passes} / ${p.n_obs}`);
      add("revision", p.revision);
      add("lat, lon, h", `${fmt(p.lat, 7)}, ${fmt(p.lon, 7)}, ${fmt(p.h, 1)} m`);
      add("sigma E, N, U", `${fmt(p.sigma_e_m, 2)}, ${fmt(p.sigma_n_m, 2)}, ${fmt(p.sigma_u_m, 2)} m`);
      add("95 % ellipse", `${fmt(p.ellipse_major_m, 2)} x ${fmt(p.ellipse_minor_m, 2)} m, major axis ${fmt(p.ellipse_azimuth_deg, 0)}°`);
      add("facing", p.facing_deg === null ? "unknown" : `${fmt(p.facing_deg, 0)}° ± ${fmt(p.facing_sigma_deg, 0)}°`);
      add("updated (solver)", time(p.updated_at));
    } else {
      rows.push(el("tr", {}, el("td", {}, "not on the map now")));
    }
    const hist = el(
      "table",
      { class: "history" },
      el("thead", {}, el("tr", {}, ...["seen", "rev", "passes", "status", "σE,σN m", "95% m", "moved"].map((h) => el("th", {}, h)))),
    );
    const tb = el("tbody");
    let prev = null;
    for (const h of entries) {
      if (h.removed) {
        tb.append(el("tr", { class: "removed" }, el("td", {}, time(h.seen_at)), el("td", {}, h.revision), el("td", { colspan: "5" }, "removed (or left the area)")));
        continue;
      }
      let moved = "–";
      if (prev) {
        const dn = (h.lat - prev.lat) * 111320;
        const de = (h.lon - prev.lon) * 111320 * Math.cos((h.lat * Math.PI) / 180);
        moved = Math.hypot(dn, de).toFixed(2);
      }
      prev = h;
      tb.append(
        el(
          "tr",
          {},
          el("td", {}, time(h.seen_at)),
          el("td", {}, h.revision),
          el("td", {}, h.passes),
          el("td", {}, h.status),
          el("td", {}, `${fmt(h.sigma_e_m, 2)},${fmt(h.sigma_n_m, 2)}`),
          el("td", {}, fmt(h.ellipse_major_m, 2)),
          el("td", {}, moved),
        ),
      );
    }
    hist.append(tb);
    body.replaceChildren(
      el("table", { class: "props" }, ...rows),
      el("p", { class: "muted" }, `History as seen by this dashboard (${entries.length} versions):`),
      hist,
    );
  }
})();
