// The live map page of fischer-gateway's map sink (docs/map.md).
// It reads the change stream (/api/stream), keeps one drawing per entity and never reads
// text from the stream as HTML: labels are set with textContent only.
(function () {
  "use strict";

  const LAYERS = ["order", "detection", "cue", "blue", "track", "airframe"];
  const SYMBOL_LAYERS = ["airframe", "track", "blue", "cue"];
  const LEADER_S = 60; // a course/speed leader shows where the entity is in this many seconds

  const map = L.map("map", { zoomControl: true, preferCanvas: true, worldCopyJump: true });
  L.control.scale({ imperial: false }).addTo(map);
  map.setView([62.0, 17.0], 5);
  const groups = {};
  for (const layer of LAYERS) groups[layer] = L.layerGroup().addTo(map);
  const drawn = {}; // layer -> id -> {marker, extras: [], data}
  for (const layer of LAYERS) drawn[layer] = new Map();
  const symbolCache = new Map();
  const state = {
    seq: 0, snapshots: 0, changes: 0, fitted: false, connected: false,
    mode: "live", replays: 0, replayAt: null, baseKind: null,
  };

  // -- base map: the node's own tiles when it has them, else world-atlas land; offline -----
  function worldAtlas() {
    fetch("/static/vendor/world-atlas/land-50m.json")
      .then((r) => r.json())
      .then((topo) => {
        const land = topojson.feature(topo, topo.objects.land);
        unwrapAll(land);
        L.geoJSON(land, {
          interactive: false,
          style: { color: "#7d8b6a", weight: 0.6, fillColor: "#eef0e4", fillOpacity: 1 },
        }).addTo(map).bringToBack();
        state.baseKind = "world-atlas";
        state.baseMap = true;
      })
      .catch(() => { state.baseMap = false; });
  }

  function localTiles(tiles) {
    const layer = L.tileLayer("/tiles/{z}/{x}/{y}", {
      minZoom: 0,
      maxZoom: 19,
      minNativeZoom: tiles.min_zoom,
      maxNativeZoom: tiles.max_zoom,
      attribution: "",
    });
    state.tilesLoaded = 0;
    layer.on("tileload", () => {
      state.tilesLoaded += 1;
      state.baseKind = "tiles";
      state.baseMap = true;
    });
    layer.addTo(map).bringToBack();
    if (tiles.attribution) {
      // The credit is the operator's text: shown as text, never as HTML.
      const Credit = L.Control.extend({
        onAdd() {
          const el = L.DomUtil.create("div", "fg-credit");
          el.textContent = tiles.attribution;
          return el;
        },
      });
      new Credit({ position: "bottomright" }).addTo(map);
    }
  }

  // world-atlas is made for spherical drawing: its rings cross the antimeridian (Chukotka) and
  // Antarctica's goes round the pole. On a flat map such a ring would get an edge across the
  // whole world, so keep each ring's longitudes continuous (beyond ±180 where it crosses), and
  // close a ring round the pole along the map's bottom edge.
  function unwrap(ring) {
    let offset = 0;
    let previous = null;
    const out = ring.map(([lon, lat]) => {
      let x = lon + offset;
      if (previous !== null && x - previous > 180) { offset -= 360; x -= 360; }
      else if (previous !== null && x - previous < -180) { offset += 360; x += 360; }
      previous = x;
      return [x, lat];
    });
    if (offset !== 0) {
      const pole = out[0][1] < 0 ? -89.9 : 89.9;
      out.push([out[out.length - 1][0], pole], [out[0][0], pole], out[0]);
    }
    // Back into the world copy where most of the ring lies (Eurasia starts in Chukotka).
    const mean = out.reduce((sum, p) => sum + p[0], 0) / out.length;
    const shift = -360 * Math.round(mean / 360);
    return shift === 0 ? out : out.map(([x, y]) => [x + shift, y]);
  }
  function unwrapAll(geo) {
    if (geo.type === "FeatureCollection") geo.features.forEach(unwrapAll);
    else if (geo.type === "Feature") unwrapAll(geo.geometry);
    else if (geo.type === "GeometryCollection") geo.geometries.forEach(unwrapAll);
    else if (geo.type === "Polygon") geo.coordinates = geo.coordinates.map(unwrap);
    else if (geo.type === "MultiPolygon") geo.coordinates = geo.coordinates.map((p) => p.map(unwrap));
  }

  // -- symbols ---------------------------------------------------------------------------
  function symbolIcon(sidc, layer, extraClass) {
    const key = sidc + "|" + layer;
    let made = symbolCache.get(key);
    if (made === undefined) {
      const size = layer === "cue" ? 18 : 22;
      const sym = new ms.Symbol(sidc, { size: size });
      const anchor = sym.getAnchor();
      const dims = sym.getSize();
      made = { svg: sym.asSVG(), anchor: [anchor.x, anchor.y], size: [dims.width, dims.height] };
      symbolCache.set(key, made);
    }
    return L.divIcon({
      className: "fg-symbol fg-layer-" + layer + (extraClass ? " " + extraClass : ""),
      html: made.svg,
      iconSize: made.size,
      iconAnchor: made.anchor,
    });
  }

  function ahead(lat, lon, courseDeg, metres) {
    const r = 6371008.8;
    const d = metres / r;
    const b = (courseDeg * Math.PI) / 180;
    const p1 = (lat * Math.PI) / 180;
    const l1 = (lon * Math.PI) / 180;
    const p2 = Math.asin(Math.sin(p1) * Math.cos(d) + Math.cos(p1) * Math.sin(d) * Math.cos(b));
    const l2 = l1 + Math.atan2(Math.sin(b) * Math.sin(d) * Math.cos(p1), Math.cos(d) - Math.sin(p1) * Math.sin(p2));
    return [(p2 * 180) / Math.PI, (((l2 * 180) / Math.PI + 540) % 360) - 180];
  }

  function label(lines) {
    const el = document.createElement("div");
    el.className = "fg-label";
    for (const line of lines) {
      if (line === null || line === undefined || line === "") continue;
      const row = document.createElement("div");
      row.textContent = String(line);
      el.appendChild(row);
    }
    return el;
  }

  function fmt(value, unit, digits) {
    return value === null || value === undefined ? "?" : value.toFixed(digits || 0) + unit;
  }

  function describe(layer, e) {
    switch (layer) {
      case "airframe": {
        const links = Object.entries(e.links || {}).map(
          ([name, l]) => name + (l.up ? " up" : " down") + (l.active ? " (active)" : "") + " loss " + fmt(l.loss_pct, "%", 0));
        return [e.id, e.origin_node ? "from node " + e.origin_node : null,
          "battery " + fmt(e.battery_pct, " %", 0) + ", endurance " + fmt(e.endurance_min, " min", 0),
          "link " + (e.active_link || "?"), ...links];
      }
      case "track":
        return [e.id + " " + e.object_class + (e.subtype ? " (" + e.subtype + ")" : ""),
          e.hostility + ", confidence " + fmt(e.confidence * 100, " %", 0),
          "CEP50 " + fmt(e.cep50_m, " m", 0) + ", CEP90 " + fmt(e.cep90_m, " m", 0),
          "course " + fmt(e.course_deg, "°", 0) + ", speed " + fmt(e.speed_mps, " m/s", 1), "SIDC " + e.sidc,
          (e.origin_nodes || []).length ? "detections from nodes " + e.origin_nodes.join(", ") : null];
      case "blue":
        return [e.callsign || e.id, "source " + e.source + " (" + e.provenance + ")"];
      case "cue":
        return ["cue " + e.id + " r" + e.revision + " " + e.status, "battery " + e.battery + " → track " + e.track_id,
          e.clear ? "deconfliction clear" : "NOT clear" + (e.nearest_blue_callsign ? ": " + e.nearest_blue_callsign + " at " + fmt(e.nearest_blue_m, " m", 0) : ""),
          "recommended " + (e.recommended_effector || "none"), e.note,
          e.origin_node ? "from node " + e.origin_node : null];
      case "order":
        return ["order " + e.order_id + " (" + e.source + ")", (e.task || "?") + ": " + e.status, e.reason,
          e.origin_node ? "from node " + e.origin_node : null];
      case "detection":
        return [e.object_class + " by " + e.airframe + " (" + e.sensor + ")", "confidence " + fmt(e.confidence * 100, " %", 0),
          e.origin_node ? "from node " + e.origin_node : null];
      default:
        return [e.id];
    }
  }

  // -- drawing ---------------------------------------------------------------------------
  // One item per entity: its marker (a symbol, a dot or an area) and its extras (CEP circle,
  // history, leader, cue line), each updated in place when the entity changes.
  function remove(layer, id) {
    const item = drawn[layer].get(id);
    if (item === undefined) return;
    if (item.marker !== null) groups[layer].removeLayer(item.marker);
    for (const extra of Object.values(item.extras)) groups[layer].removeLayer(extra);
    drawn[layer].delete(id);
    renderLists(layer);
  }

  function setExtra(layer, item, name, wanted, make, update) {
    const have = item.extras[name];
    if (!wanted) {
      if (have !== undefined) { groups[layer].removeLayer(have); delete item.extras[name]; }
      return;
    }
    if (have === undefined) {
      item.extras[name] = make();
      groups[layer].addLayer(item.extras[name]);
    } else {
      update(have);
    }
  }

  function updateExtras(layer, item, e) {
    const here = [e.lat, e.lon];
    const red = "#c0392b";
    if (layer === "track") {
      setExtra(layer, item, "cep", e.cep50_m > 0,
        () => L.circle(here, { radius: e.cep50_m, color: red, weight: 1, fillOpacity: 0.08, interactive: false }),
        (c) => { c.setLatLng(here); c.setRadius(e.cep50_m); });
      setExtra(layer, item, "history", e.history && e.history.length > 1,
        () => L.polyline(e.history, { color: red, weight: 1, opacity: 0.6, dashArray: "2 3", interactive: false }),
        (l) => l.setLatLngs(e.history));
    }
    if (layer === "track" || layer === "blue" || layer === "airframe") {
      const course = layer === "airframe" ? e.heading_deg : e.course_deg;
      const speed = layer === "airframe" ? e.groundspeed_mps : e.speed_mps;
      const wanted = course !== null && course !== undefined && !!speed;
      const line = () => [here, ahead(e.lat, e.lon, course, speed * LEADER_S)];
      setExtra(layer, item, "leader", wanted,
        () => L.polyline(line(), { color: layer === "track" ? red : "#1f5fa8", weight: 2, interactive: false }),
        (l) => l.setLatLngs(line()));
    }
    if (layer === "cue") {
      const held = !e.clear || e.status !== "active";
      const style = { color: held ? "#a31515" : "#d35400", weight: 2, dashArray: held ? "6 4" : null, interactive: false };
      setExtra(layer, item, "line", true,
        () => L.polyline([[e.battery_lat, e.battery_lon], here], style),
        (l) => { l.setLatLngs([[e.battery_lat, e.battery_lon], here]); l.setStyle(style); });
    }
  }

  function makeMarker(layer, e, item) {
    let marker;
    if (layer === "detection") {
      marker = L.circleMarker([e.lat, e.lon], { radius: 3, color: "#6c3483", weight: 1, fillOpacity: 0.7, className: "fg-detection" });
    } else if (layer === "order") {
      marker = e.polygon && e.polygon.length >= 3
        ? L.polygon(e.polygon, { color: "#117a65", weight: 2, fillOpacity: 0.05, className: "fg-order" })
        : L.circleMarker([e.lat, e.lon], { radius: 9, color: "#117a65", weight: 2, fillOpacity: 0, className: "fg-order" });
    } else {
      marker = L.marker(symbolAt(layer, e), { icon: symbolIcon(e.sidc, layer, iconClass(layer, e)), keyboard: false });
    }
    // The tooltip is built when shown, from the entity's state then.
    marker.bindTooltip(() => label(describe(layer, item.data)), { direction: "top" });
    return marker;
  }

  function symbolAt(layer, e) {
    return layer === "cue" ? [e.battery_lat, e.battery_lon] : [e.lat, e.lon];
  }

  function iconClass(layer, e) {
    return layer === "cue" && (!e.clear || e.status !== "active") ? "fg-held" : "";
  }

  function upsert(layer, e) {
    const placed = e.lat !== null && e.lat !== undefined;
    const key = e.sidc + iconClass(layer, e);
    let item = drawn[layer].get(e.id);
    // An order's shape, and an entity gaining or losing its position, are drawn anew.
    if (item !== undefined && (layer === "order" || !placed || item.marker === null)) {
      remove(layer, e.id);
      item = undefined;
    }
    if (item === undefined) {
      item = { marker: null, extras: {}, data: e, iconKey: key };
      drawn[layer].set(e.id, item);
      if (placed) {
        item.marker = makeMarker(layer, e, item);
        groups[layer].addLayer(item.marker);
      }
    } else {
      item.data = e;
      item.marker.setLatLng(symbolAt(layer, e));
      if (layer !== "detection" && item.iconKey !== key) {
        item.marker.setIcon(symbolIcon(e.sidc, layer, iconClass(layer, e)));
        item.iconKey = key;
      }
    }
    if (placed) updateExtras(layer, item, e);
    renderLists(layer);
  }

  function clearAll() {
    for (const layer of LAYERS) {
      groups[layer].clearLayers();
      drawn[layer].clear();
      renderLists(layer);
    }
  }

  function fit() {
    const points = [];
    for (const layer of SYMBOL_LAYERS) for (const item of drawn[layer].values()) if (item.marker !== null) points.push([item.data.lat, item.data.lon]);
    if (points.length === 0) return false;
    map.fitBounds(L.latLngBounds(points).pad(0.25), { maxZoom: 14, animate: false });
    return true;
  }

  // -- side lists ------------------------------------------------------------------------
  const lists = { cue: "cues", order: "orders", airframe: "airframes" };
  const pendingLists = new Set();
  function renderLists(layer) {
    if (!(layer in lists)) return;
    if (pendingLists.size === 0) requestAnimationFrame(flushLists);
    pendingLists.add(layer);
  }
  function flushLists() {
    for (const layer of pendingLists) {
      const ul = document.getElementById(lists[layer]);
      ul.replaceChildren();
      const items = Array.from(drawn[layer].values()).slice(-50).reverse();
      for (const item of items) {
        const e = item.data;
        const li = document.createElement("li");
        if (layer === "cue") li.className = e.status !== "active" ? "stale" : (e.clear ? "" : "held");
        const lines = describe(layer, e);
        const head = document.createElement("div");
        head.textContent = lines[0];
        const sub = document.createElement("div");
        sub.className = "sub";
        sub.textContent = lines.slice(1).filter((x) => x).join(" · ");
        li.append(head, sub);
        ul.appendChild(li);
      }
    }
    pendingLists.clear();
  }

  let countsPending = false;
  function showCounts() {
    if (countsPending) return;
    countsPending = true;
    requestAnimationFrame(() => { countsPending = false; writeCounts(); });
  }
  function writeCounts() {
    const parts = SYMBOL_LAYERS.map((layer) => layer + " " + drawn[layer].size);
    document.getElementById("counts").textContent = parts.join(" · ");
  }

  // -- the stream ------------------------------------------------------------------------
  function applyChange(change) {
    if (change.op === "remove") remove(change.layer, change.id);
    else upsert(change.layer, change.data);
    state.seq = change.seq;
    state.changes += 1;
  }

  let source = null;
  const linkEl = document.getElementById("link");

  function connect() {
    source = new EventSource("/api/stream");
    source.addEventListener("open", () => { state.connected = true; linkEl.textContent = "live"; linkEl.className = "up"; });
    source.addEventListener("error", () => { state.connected = false; linkEl.textContent = "reconnecting"; linkEl.className = "down"; });
    source.addEventListener("snapshot", (msg) => {
      if (state.mode !== "live") return;
      const snap = JSON.parse(msg.data);
      document.getElementById("title").textContent = snap.title;
      drawAll(snap.layers);
      state.seq = snap.seq;
      state.snapshots += 1;
      if (!state.fitted) state.fitted = fit();
    });
    source.addEventListener("change", (msg) => {
      if (state.mode !== "live") return;
      applyChange(JSON.parse(msg.data));
      if (!state.fitted) state.fitted = fit();
      showCounts();
    });
    source.addEventListener("overflow", () => { linkEl.textContent = "catching up"; });
  }

  function drawAll(layers) {
    clearAll();
    for (const layer of LAYERS) for (const e of layers[layer] || []) upsert(layer, e);
    showCounts();
  }

  // -- the time slider: the picture as it was, from the node's archive ---------------------
  // Dragging back leaves the live stream and asks the node for the picture at that instant
  // (GET /api/picture?at=...); "Live" (or the slider's right end) returns to the stream.
  const historyBar = document.getElementById("history");
  const slider = document.getElementById("time");
  const whenEl = document.getElementById("when");
  const liveButton = document.getElementById("live");
  const span = { start: null, offset: 0 };
  let asked = 0;
  let pending = null;
  let scrubbing = false; // the operator is moving the slider: the clock leaves it alone

  function instant(value) {
    return new Date(span.start + (value === undefined ? Number(slider.value) : value) * 1000);
  }
  function stamp(date) {
    return date.toISOString().replace(/\.\d{3}Z$/, "Z");
  }

  // The archive's span: its first event (asked of the node), to now (the node's clock).
  function refreshSpan() {
    return fetch("/api/archive")
      .then((r) => (r.ok ? r.json() : null))
      .then((body) => {
        if (body === null || body.start === null) return;
        span.start = Date.parse(body.start);
        span.offset = Date.parse(body.now) - Date.now();
        historyBar.hidden = false;
        state.archiveStart = body.start;
        tick();
      })
      .catch(() => {});
  }
  function tick() {
    if (span.start === null) return;
    slider.max = String(Math.max(0, Math.floor((Date.now() + span.offset - span.start) / 1000)));
    if (state.mode === "live" && !scrubbing) slider.value = slider.max;
  }

  function showAt(date) {
    const at = stamp(date);
    const ticket = ++asked;
    state.mode = "replay";
    if (source !== null) { source.close(); source = null; }
    state.connected = false;
    linkEl.textContent = "archive";
    linkEl.className = "past";
    whenEl.textContent = at.replace("T", " ");
    whenEl.className = "past";
    liveButton.disabled = false;
    fetch("/api/picture?at=" + encodeURIComponent(at))
      .then((r) => r.json().then((body) => ({ ok: r.ok, body })))
      .then(({ ok, body }) => {
        if (ticket !== asked || state.mode !== "replay") return; // a newer question, or live again
        if (!ok) { whenEl.textContent = body.error || "no picture"; return; }
        drawAll(body.layers);
        state.replayAt = body.at;
        state.replay = body.replay;
        state.replays += 1;
        if (body.replay.truncated) whenEl.textContent += " (partial)";
      })
      .catch(() => { if (ticket === asked) whenEl.textContent = "no answer"; });
  }

  function goLive() {
    asked += 1;
    state.mode = "live";
    state.replayAt = null;
    whenEl.textContent = "live";
    whenEl.className = "";
    liveButton.disabled = true;
    slider.value = slider.max;
    if (source === null) connect();
  }

  slider.addEventListener("pointerdown", () => { scrubbing = true; refreshSpan(); });
  slider.addEventListener("pointerup", () => { setTimeout(() => { scrubbing = false; }, 0); });
  slider.addEventListener("input", () => {
    scrubbing = true;
    whenEl.textContent = stamp(instant()).replace("T", " ");
    clearTimeout(pending);
    pending = setTimeout(() => { slider.dispatchEvent(new Event("change")); }, 300);
  });
  slider.addEventListener("change", () => {
    clearTimeout(pending);
    scrubbing = false;
    if (span.start === null) return;
    const value = Number(slider.value);
    tick(); // the right end is now, not when the clock last moved it
    if (value >= Number(slider.max)) goLive();
    else { slider.value = String(value); showAt(instant(value)); }
  });
  liveButton.addEventListener("click", goLive);

  fetch("/api/info")
    .then((r) => r.json())
    .then((info) => {
      document.getElementById("title").textContent = info.title;
      if (info.tiles) localTiles(info.tiles);
      else worldAtlas();
      if (info.archive) {
        refreshSpan();
        // Until the archive holds an event, ask again; then the slider's end follows the clock.
        setInterval(() => { if (span.start === null) refreshSpan(); else tick(); }, 1000);
      }
    })
    .catch(() => worldAtlas());

  connect();
  document.getElementById("fit").addEventListener("click", () => { fit(); });

  // -- MGRS under the cursor, asked of the node (at most one question in flight) -----------
  let asking = false;
  let wanted = null;
  const mgrsEl = document.getElementById("mgrs");
  function ask() {
    if (asking || wanted === null) return;
    const at = wanted;
    wanted = null;
    asking = true;
    fetch("/api/mgrs?lat=" + at.lat.toFixed(6) + "&lon=" + at.lng.toFixed(6))
      .then((r) => r.json())
      .then((body) => { mgrsEl.textContent = "MGRS " + (body.mgrs || "—"); })
      .catch(() => {})
      .finally(() => { asking = false; ask(); });
  }
  map.on("mousemove", (ev) => {
    wanted = L.latLng(ev.latlng.lat, ((ev.latlng.lng + 540) % 360) - 180);
    ask();
  });

  // -- for tests and integrators' own checks ----------------------------------------------
  window.fgMap = {
    state: state,
    map: map,
    symbols: () => document.querySelectorAll(".fg-symbol").length,
    count: (layer) => drawn[layer].size,
    position: (layer, id) => {
      const item = drawn[layer].get(id);
      if (item === undefined || item.marker === null || !item.marker.getLatLng) return null;
      const p = map.latLngToContainerPoint(item.marker.getLatLng());
      return { lat: item.data.lat, lon: item.data.lon, x: p.x, y: p.y };
    },
    ids: (layer) => Array.from(drawn[layer].keys()),
    // The slider's value (seconds after the archive's start) for an instant.
    sliderValueFor: (iso) => Math.round((Date.parse(iso) - span.start) / 1000),
  };
})();
