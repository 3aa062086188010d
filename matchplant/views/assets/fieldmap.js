// MatchPlant field map: the plants on one canvas (not one element per plant), coloured by a trait, with a
// legend, a histogram, the plots, popups with each plant's traits and crops, and a search box.
// DATA comes from matchplant/views/fieldmap.py; coordinates are metres from DATA.origin (x east, y north).
(function () {
  "use strict";
  const D = DATA;
  const n = D.plants.ids.length;
  const off = D.plants.offsets;
  const xy = D.plants.coords; // centimetres, x then y, every plant's ring after the other
  const RAMP = [[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]]; // viridis

  function rampColour(t) {
    if (!(t >= 0)) return [150, 150, 150];
    const s = Math.min(t, 1) * (RAMP.length - 1);
    const i = Math.min(Math.floor(s), RAMP.length - 2);
    const f = s - i;
    return RAMP[i].map((c, k) => Math.round(c + f * (RAMP[i + 1][k] - c)));
  }

  // each plant's box (metres), for culling and for the click's lookup grid
  const box = new Float64Array(4 * n);
  for (let p = 0; p < n; p++) {
    let x0 = Infinity, y0 = Infinity, x1 = -Infinity, y1 = -Infinity;
    for (let k = off[p]; k < off[p + 1]; k++) {
      const x = xy[2 * k] / 100, y = xy[2 * k + 1] / 100;
      if (x < x0) x0 = x; if (x > x1) x1 = x; if (y < y0) y0 = y; if (y > y1) y1 = y;
    }
    box.set([x0, y0, x1, y1], 4 * p);
  }
  const CELL = D.cell;
  const grid = new Map();
  for (let p = 0; p < n; p++) {
    for (let i = Math.floor(box[4 * p] / CELL); i <= Math.floor(box[4 * p + 2] / CELL); i++)
      for (let j = Math.floor(box[4 * p + 1] / CELL); j <= Math.floor(box[4 * p + 3] / CELL); j++) {
        const key = i + "," + j;
        if (!grid.has(key)) grid.set(key, []);
        grid.get(key).push(p);
      }
  }

  function inRing(x, y, coords, a, b, scale) {
    let inside = false;
    for (let k = a, m = b - 1; k < b; m = k++) {
      const xi = coords[2 * k] / scale, yi = coords[2 * k + 1] / scale;
      const xj = coords[2 * m] / scale, yj = coords[2 * m + 1] / scale;
      if ((yi > y) !== (yj > y) && x < ((xj - xi) * (y - yi)) / (yj - yi) + xi) inside = !inside;
    }
    return inside;
  }

  function plantAt(x, y) {
    const cands = grid.get(Math.floor(x / CELL) + "," + Math.floor(y / CELL)) || [];
    for (const p of cands) if (inRing(x, y, xy, off[p], off[p + 1], 100)) return p;
    return -1;
  }

  // -- the map (CRS.Simple: one unit a metre; lat is north) -------------------------------------------
  const map = L.map("map", { crs: L.CRS.Simple, minZoom: -6, maxZoom: 12, zoomSnap: 0.25, zoomAnimation: false, fadeAnimation: false, preferCanvas: true });
  const W = D.extent[2], H = D.extent[3];
  if (D.ortho) L.imageOverlay(D.ortho.src, [[D.ortho.bounds[1], D.ortho.bounds[0]], [D.ortho.bounds[3], D.ortho.bounds[2]]]).addTo(map);
  map.fitBounds([[0, 0], [H, W]]);

  let trait = D.default_trait;
  let colours = new Array(n);
  let range = [0, 1];

  function recolour() {
    const v = trait ? D.plants.traits[trait] : null;
    let lo = Infinity, hi = -Infinity;
    if (v) for (const x of v) if (x !== null && isFinite(x)) { if (x < lo) lo = x; if (x > hi) hi = x; }
    range = [lo, hi];
    const span = hi > lo ? hi - lo : 1;
    for (let p = 0; p < n; p++) {
      const x = v ? v[p] : null;
      const c = rampColour(x === null || !isFinite(x) ? NaN : (x - lo) / span);
      colours[p] = "rgb(" + c.join(",") + ")";
    }
    drawLegend();
  }

  const PlantLayer = L.Layer.extend({
    onAdd: function (m) {
      this._canvas = L.DomUtil.create("canvas", "plants");
      m.getPanes().overlayPane.appendChild(this._canvas);
      m.on("moveend zoomend resize viewreset", this.redraw, this);
      this.redraw();
    },
    onRemove: function (m) {
      L.DomUtil.remove(this._canvas);
      m.off("moveend zoomend resize viewreset", this.redraw, this);
    },
    redraw: function () {
      const m = this._map, size = m.getSize(), dpr = window.devicePixelRatio || 1;
      const c = this._canvas;
      L.DomUtil.setPosition(c, m.containerPointToLayerPoint([0, 0]));
      c.width = size.x * dpr; c.height = size.y * dpr;
      c.style.width = size.x + "px"; c.style.height = size.y + "px";
      const ctx = c.getContext("2d");
      ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
      const o = m.latLngToContainerPoint([0, 0]);
      const s = m.getZoomScale(m.getZoom(), 0);
      const b = m.getBounds();
      const vx0 = b.getWest(), vx1 = b.getEast(), vy0 = b.getSouth(), vy1 = b.getNorth();
      const buckets = new Map();
      let drawn = 0;
      for (let p = 0; p < n; p++) {
        if (box[4 * p + 2] < vx0 || box[4 * p] > vx1 || box[4 * p + 3] < vy0 || box[4 * p + 1] > vy1) continue;
        const key = colours[p];
        if (!buckets.has(key)) buckets.set(key, []);
        buckets.get(key).push(p);
        drawn++;
      }
      ctx.lineWidth = 1;
      ctx.globalAlpha = 0.75;
      const k = s / 100;
      for (const [colour, list] of buckets) {
        ctx.beginPath();
        for (const p of list) {
          for (let q = off[p]; q < off[p + 1]; q++) {
            const px = o.x + xy[2 * q] * k, py = o.y - xy[2 * q + 1] * k;
            if (q === off[p]) ctx.moveTo(px, py); else ctx.lineTo(px, py);
          }
          ctx.closePath();
        }
        ctx.fillStyle = colour;
        ctx.fill();
        if (s > 40) { ctx.strokeStyle = "rgba(255,255,255,0.8)"; ctx.stroke(); }
      }
      window.fieldmap.drawn = drawn;
      window.fieldmap.redraws += 1;
    },
  });

  // -- plots: few, drawn by Leaflet's canvas renderer --------------------------------------------------
  const plots = [];
  if (D.plots) {
    const P = D.plots;
    for (let i = 0; i < P.ids.length; i++) {
      const ring = [];
      for (let q = P.offsets[i]; q < P.offsets[i + 1]; q++) ring.push([P.coords[2 * q + 1] / 100, P.coords[2 * q] / 100]);
      plots.push(L.polygon(ring, { color: "#ffffff", weight: 1.5, fill: false, interactive: false }).addTo(map));
    }
  }
  function plotAt(x, y) {
    if (!D.plots) return -1;
    for (let i = 0; i < D.plots.ids.length; i++)
      if (inRing(x, y, D.plots.coords, D.plots.offsets[i], D.plots.offsets[i + 1], 100)) return i;
    return -1;
  }

  // -- popups -------------------------------------------------------------------------------------------
  function esc(s) {
    return String(s).replace(/[&<>"]/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;" })[c]);
  }
  function fmt(v) {
    return v === null || v === undefined ? "–" : typeof v === "number" ? (Number.isInteger(v) ? v : v.toPrecision(4)) : esc(v);
  }
  function table(rows) {
    return "<table>" + rows.map(([k, v]) => "<tr><th>" + esc(k) + "</th><td>" + fmt(v) + "</td></tr>").join("") + "</table>";
  }
  function plantHtml(p) {
    const rows = [["plant", D.plants.ids[p]]];
    for (const t of Object.keys(D.plants.traits)) rows.push([t, D.plants.traits[t][p]]);
    let html = "<div class='plant-popup' data-plant='" + esc(D.plants.ids[p]) + "'><b>Plant " + esc(D.plants.ids[p]) + "</b>" + table(rows);
    const crops = D.crops ? D.crops[D.plants.ids[p]] : null;
    if (crops && crops.length) {
      html += "<div class='crops'>";
      for (const [src, angle, outline, w, h] of crops) {
        html += "<figure><svg viewBox='-0.5 -0.5 " + w + " " + h + "' width='" + Math.min(120, w * 2) + "'>" +
          "<image href='" + esc(src) + "' x='-0.5' y='-0.5' width='" + w + "' height='" + h + "'/>" +
          (outline ? "<polygon points='" + outline + "'/>" : "") + "</svg><figcaption>" + angle.toFixed(1) + "°</figcaption></figure>";
      }
      html += "</div>";
    }
    return html + "</div>";
  }
  function plotHtml(i) {
    const rows = [["plot", D.plots.ids[i]]];
    for (const t of Object.keys(D.plots.stats)) rows.push([t, D.plots.stats[t][i]]);
    return "<div class='plot-popup' data-plot='" + esc(D.plots.ids[i]) + "'><b>Plot " + esc(D.plots.ids[i]) + "</b>" + table(rows) + "</div>";
  }
  function centre(p) {
    return L.latLng((box[4 * p + 1] + box[4 * p + 3]) / 2, (box[4 * p] + box[4 * p + 2]) / 2);
  }
  function openPlant(p, at) {
    L.popup({ maxWidth: 420 }).setLatLng(at || centre(p)).setContent(plantHtml(p)).openOn(map);
  }

  map.on("click", function (e) {
    const x = e.latlng.lng, y = e.latlng.lat;
    const p = plantAt(x, y);
    if (p >= 0) return openPlant(p, e.latlng);
    const i = plotAt(x, y);
    if (i >= 0) L.popup().setLatLng(e.latlng).setContent(plotHtml(i)).openOn(map);
  });

  // -- the panel: trait, legend, histogram, search ----------------------------------------------------
  const select = document.getElementById("trait");
  for (const t of Object.keys(D.plants.traits)) {
    const o = document.createElement("option");
    o.value = o.textContent = t;
    if (t === trait) o.selected = true;
    select.appendChild(o);
  }
  select.addEventListener("change", () => { trait = select.value; recolour(); layer.redraw(); });

  function drawLegend() {
    const lo = document.getElementById("legend-lo"), hi = document.getElementById("legend-hi");
    lo.textContent = isFinite(range[0]) ? fmt(range[0]) : "–";
    hi.textContent = isFinite(range[1]) ? fmt(range[1]) : "–";
    const cv = document.getElementById("histogram"), ctx = cv.getContext("2d");
    ctx.clearRect(0, 0, cv.width, cv.height);
    const v = trait ? D.plants.traits[trait] : null;
    if (!v || !(range[1] >= range[0])) return;
    const bins = 30, counts = new Array(bins).fill(0), span = range[1] > range[0] ? range[1] - range[0] : 1;
    for (const x of v) if (x !== null && isFinite(x)) counts[Math.min(bins - 1, Math.floor(((x - range[0]) / span) * bins))]++;
    const top = Math.max(...counts), bw = cv.width / bins;
    counts.forEach((c, i) => {
      ctx.fillStyle = "rgb(" + rampColour((i + 0.5) / bins).join(",") + ")";
      const h = top ? (c / top) * (cv.height - 2) : 0;
      ctx.fillRect(i * bw, cv.height - h, bw - 1, h);
    });
  }

  const search = document.getElementById("search"), msg = document.getElementById("search-msg");
  const plantIndex = new Map(D.plants.ids.map((id, p) => [String(id), p]));
  const plotIndex = D.plots ? new Map(D.plots.ids.map((id, i) => [String(id), i])) : new Map();
  search.addEventListener("keydown", (e) => {
    if (e.key !== "Enter") return;
    const q = search.value.trim();
    if (plantIndex.has(q)) {
      const p = plantIndex.get(q);
      map.setView(centre(p), Math.max(map.getZoom(), 5));
      openPlant(p);
      msg.textContent = "";
    } else if (plotIndex.has(q)) {
      const i = plotIndex.get(q);
      map.fitBounds(plots[i].getBounds());
      L.popup().setLatLng(plots[i].getBounds().getCenter()).setContent(plotHtml(i)).openOn(map);
      msg.textContent = "";
    } else msg.textContent = "no plant or plot " + q;
  });

  window.fieldmap = { map: map, plants: n, drawn: 0, redraws: 0, plantAt: plantAt, ready: false };
  recolour();
  const layer = new PlantLayer().addTo(map);
  window.fieldmap.ready = true;
})();
