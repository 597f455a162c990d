// seqvpr view: the page's script. Reads the run's data from #data and draws the route, the distances (a match's
// top-K band with the ground truth, zoomable) or the timeline (a localisation), and the selected frame beside its
// matches. Keys: arrows step a frame, n / p step to the next / previous failure, + / - zoom the distances.
(function () {
  'use strict';
  const D = JSON.parse(document.getElementById('data').textContent);
  const C = { right: '#2e7d32', wrong: '#c62828', none: '#9e9e9e', lost: '#ff8f00', ref: '#b0bec5', sel: '#1565c0',
              band: '#c8e6c9', cell: '#90a4ae' };
  const SHOWN = 5;
  const S = { sel: 0, method: 0, zoom: 1, cx: 0.5, cy: 0.5, drag: null };
  const route = document.getElementById('route'), second = document.getElementById('second');
  const query = D.query || null, reference = D.reference;
  const nQuery = query ? query.names.length : 0, nRef = reference.names.length;

  function esc(text) {
    return String(text).replace(/[&<>"']/g, (c) => ({ '&': '&amp;', '<': '&lt;', '>': '&gt;', '"': '&quot;', "'": '&#39;' }[c]));
  }

  // ---- outcomes -------------------------------------------------------------------------------------------
  function outcome(q) {
    if (D.kind === 'localize') {
      const st = D.stream.status[q], ok = D.stream.correct[q];
      if (st === 'localised') return ok === 0 ? 'wrong' : (ok === 1 ? 'right' : 'none');
      return st === 'lost' ? 'lost' : 'none';
    }
    const m = D.methods[S.method];
    if (!m || m.refs[q][0] < 0) return 'none';
    return m.correct[q] === 1 ? 'right' : (m.correct[q] === 0 ? 'wrong' : 'none');
  }
  function isFailure(q) { return outcome(q) === 'wrong'; }

  // ---- route ----------------------------------------------------------------------------------------------
  function layout(side, row) {
    if (!side) return [];
    if (side.xy) return side.xy;
    return side.names.map((_, i) => [i, row]);
  }
  const refXY = layout(reference, 1), qryXY = layout(query, 0);
  const fit = (function () {
    const all = refXY.concat(qryXY);
    let x0 = Infinity, x1 = -Infinity, y0 = Infinity, y1 = -Infinity;
    for (const [x, y] of all) { x0 = Math.min(x0, x); x1 = Math.max(x1, x); y0 = Math.min(y0, y); y1 = Math.max(y1, y); }
    if (!all.length) { x0 = y0 = 0; x1 = y1 = 1; }
    const pad = 16, w = route.width - 2 * pad, h = route.height - 2 * pad;
    const ordered = !(reference.xy || (query && query.xy));
    const sx = w / Math.max(x1 - x0, 1e-9), sy = h / Math.max(y1 - y0, 1e-9);
    const s = ordered ? null : Math.min(sx, sy);
    return (p) => ordered ? [pad + (p[0] - x0) * sx, pad + h - (p[1] - y0) * sy]
                          : [pad + (p[0] - x0) * s, route.height - pad - (p[1] - y0) * s];
  })();
  function pointOf(q) { return fit(qryXY[q]); }

  // what does not change with the selection is drawn once into a layer, and the selection over a copy of it
  const layers = {};
  function layer(name, key, canvas, paint) {
    if (!layers[name] || layers[name].key !== key) {
      const off = document.createElement('canvas');
      off.width = canvas.width; off.height = canvas.height;
      paint(off.getContext('2d'));
      layers[name] = { key, canvas: off };
    }
    const g = canvas.getContext('2d');
    g.clearRect(0, 0, canvas.width, canvas.height);
    g.drawImage(layers[name].canvas, 0, 0);
    return g;
  }
  function paintRoute(g) {
    g.fillStyle = C.ref;
    for (const p of refXY) { const [x, y] = fit(p); g.fillRect(x - 1, y - 1, 2, 2); }
    for (let q = 0; q < qryXY.length; q++) {
      const [x, y] = fit(qryXY[q]);
      g.fillStyle = C[outcome(q)];
      g.fillRect(x - 1.5, y - 1.5, 3, 3);
    }
  }
  function drawRoute() {
    const g = layer('route', S.method, route, paintRoute);
    const top = matchOf(S.sel);
    if (query && top >= 0 && refXY[top]) {
      const [x0, y0] = fit(qryXY[S.sel]), [x1, y1] = fit(refXY[top]);
      g.strokeStyle = C[outcome(S.sel)]; g.lineWidth = 2;
      g.beginPath(); g.moveTo(x0, y0); g.lineTo(x1, y1); g.stroke();
    }
    if (query && qryXY[S.sel]) {
      const [x, y] = fit(qryXY[S.sel]);
      g.strokeStyle = C.sel; g.lineWidth = 2; g.beginPath(); g.arc(x, y, 7, 0, 2 * Math.PI); g.stroke();
    }
  }
  function matchOf(q) {
    if (D.kind === 'localize') return D.stream.localised[q] >= 0 ? D.stream.localised[q] : D.stream.best[q];
    const m = D.methods[S.method];
    return m ? m.refs[q][0] : -1;
  }
  route.addEventListener('click', (e) => {
    if (!query) return;
    const r = route.getBoundingClientRect(), x = e.clientX - r.left, y = e.clientY - r.top;
    let best = -1, dist = 12 * 12;
    for (let q = 0; q < qryXY.length; q++) {
      const [px, py] = fit(qryXY[q]), d = (px - x) ** 2 + (py - y) ** 2;
      if (d < dist) { dist = d; best = q; }
    }
    if (best >= 0) select(best);
  });

  // ---- distances: the top-K band of a match, zoomable -------------------------------------------------------
  function matrixView() {
    const z = S.zoom, w = second.width, h = second.height;
    const sx = (w / Math.max(nRef, 1)) * z, sy = (h / Math.max(nQuery, 1)) * z;
    const ox = w / 2 - S.cx * nRef * sx, oy = h / 2 - S.cy * nQuery * sy;
    return { sx, sy, ox, oy };
  }
  function matrixPointOf(q, r) {
    const v = matrixView();
    return [v.ox + (r + 0.5) * v.sx, v.oy + (q + 0.5) * v.sy];
  }
  // the band is drawn in tiles of TILE x TILE pixels at the zoom level 2^t just below the zoom, each made once and
  // kept, then scaled into place: panning and stepping only copy tiles, so a 10k x 10k match stays smooth
  const TILE = 256, tiles = new Map(), MAX_TILES = 600;
  function drawMatrix() {
    const v = matrixView(), t = Math.max(0, Math.floor(Math.log2(S.zoom) + 1e-9)), f = S.zoom / 2 ** t;
    const g = second.getContext('2d');
    g.clearRect(0, 0, second.width, second.height);
    g.imageSmoothingEnabled = false;
    const size = TILE * f;
    const i0 = Math.max(0, Math.floor(-v.ox / size)), i1 = Math.ceil((second.width - v.ox) / size);
    const j0 = Math.max(0, Math.floor(-v.oy / size)), j1 = Math.ceil((second.height - v.oy) / size);
    const across = Math.ceil(second.width * 2 ** t / TILE), down = Math.ceil(second.height * 2 ** t / TILE);
    for (let i = i0; i < Math.min(i1, across); i++) {
      for (let j = j0; j < Math.min(j1, down); j++) g.drawImage(tile(t, i, j), v.ox + i * size, v.oy + j * size, size, size);
    }
    g.strokeStyle = C.sel; g.lineWidth = 1;
    g.strokeRect(0, v.oy + S.sel * v.sy, second.width, Math.max(v.sy, 1));
  }
  function tile(t, i, j) {
    const key = `${S.method}/${t}/${i}/${j}`;
    let found = tiles.get(key);
    if (found) { tiles.delete(key); tiles.set(key, found); return found; }  // most recently used last
    found = document.createElement('canvas');
    found.width = found.height = TILE;
    paintTile(found.getContext('2d'), t, i, j);
    tiles.set(key, found);
    if (tiles.size > MAX_TILES) tiles.delete(tiles.keys().next().value);
    return found;
  }
  function paintTile(g, t, i, j) {
    const sx = (second.width / Math.max(nRef, 1)) * 2 ** t, sy = (second.height / Math.max(nQuery, 1)) * 2 ** t;
    const x0 = i * TILE, y0 = j * TILE, m = D.methods[S.method];
    const q0 = Math.max(0, Math.floor(y0 / sy)), q1 = Math.min(nQuery, Math.ceil((y0 + TILE) / sy));
    const r0 = Math.floor(x0 / sx) - 1, r1 = Math.ceil((x0 + TILE) / sx) + 1;
    const cw = Math.max(sx, 1), ch = Math.max(sy, 1);
    if (D.positives) {
      g.fillStyle = C.band;
      for (let q = q0; q < q1; q++) for (const r of D.positives[q] || []) {
        if (r >= r0 && r <= r1) g.fillRect(r * sx - x0, q * sy - y0, cw, ch);
      }
    }
    for (let q = q0; q < q1; q++) {
      const refs = m.refs[q];
      for (let k = refs.length - 1; k >= 0; k--) {
        const r = refs[k];
        if (r < r0 || r > r1) continue;
        g.fillStyle = k === 0 ? C[outcome(q)] : C.cell;
        g.globalAlpha = k === 0 ? 1 : 0.25 + 0.5 * (1 - k / refs.length);
        g.fillRect(r * sx - x0, q * sy - y0, cw, ch);
      }
    }
    g.globalAlpha = 1;
  }
  function zoomMatrix(factor, atX, atY) {
    const v = matrixView();
    const x = atX === undefined ? second.width / 2 : atX, y = atY === undefined ? second.height / 2 : atY;
    const r = (x - v.ox) / v.sx / Math.max(nRef, 1), q = (y - v.oy) / v.sy / Math.max(nQuery, 1);
    S.zoom = Math.min(Math.max(S.zoom * factor, 1), 4096);
    S.cx = r - (x - second.width / 2) / (second.width * S.zoom);
    S.cy = q - (y - second.height / 2) / (second.height * S.zoom);
    drawSecond();
  }

  function zoomAtSelection(factor) {
    // the keys zoom about the selected query and its top-1: what is being looked at stays in view
    const top = matchOf(S.sel);
    S.cy = (S.sel + 0.5) / Math.max(nQuery, 1);
    if (top >= 0) S.cx = (top + 0.5) / Math.max(nRef, 1);
    zoomMatrix(factor);
  }

  // ---- timeline: a localisation's score and status ---------------------------------------------------------
  function timelineX(i) { return 8 + (i + 0.5) * (second.width - 16) / Math.max(nQuery, 1); }
  function drawTimeline() {
    const g = layer('timeline', 0, second, paintTimeline);
    g.strokeStyle = C.sel; g.beginPath(); g.moveTo(timelineX(S.sel), 0); g.lineTo(timelineX(S.sel), second.height);
    g.stroke();
  }
  function paintTimeline(g) {
    const st = D.stream, h = second.height - 30;
    const scores = st.score.filter((s) => s !== null);
    const top = scores.reduce((a, b) => Math.max(a, b), Math.max(1e-9, st.threshold || 0));
    for (let i = 0; i < nQuery; i++) {
      g.fillStyle = C[outcome(i)];
      g.fillRect(timelineX(i) - 1, h + 8, Math.max(2, (second.width - 16) / nQuery), 14);
    }
    g.strokeStyle = '#1565c0'; g.beginPath();
    let started = false;
    st.score.forEach((s, i) => {
      if (s === null) { started = false; return; }
      const y = h - (s / top) * (h - 10);
      if (started) g.lineTo(timelineX(i), y); else { g.moveTo(timelineX(i), y); started = true; }
    });
    g.stroke();
    if (st.threshold !== null && st.threshold !== undefined) {
      const y = h - (st.threshold / top) * (h - 10);
      g.strokeStyle = '#ff8f00'; g.setLineDash([4, 4]); g.beginPath(); g.moveTo(0, y); g.lineTo(second.width, y);
      g.stroke(); g.setLineDash([]);
    }
  }
  function frameAtX(x) {
    return Math.min(nQuery - 1, Math.max(0, Math.floor((x - 8) * nQuery / (second.width - 16))));
  }

  function drawSecond() {
    if (D.kind === 'match') drawMatrix(); else if (D.kind === 'localize') drawTimeline();
  }
  second.addEventListener('mousedown', (e) => {
    const r = second.getBoundingClientRect();
    S.drag = { x: e.clientX - r.left, y: e.clientY - r.top, cx: S.cx, cy: S.cy, moved: false };
  });
  second.addEventListener('mousemove', (e) => {
    if (!S.drag) return;
    const r = second.getBoundingClientRect(), x = e.clientX - r.left, y = e.clientY - r.top;
    if (Math.abs(x - S.drag.x) + Math.abs(y - S.drag.y) > 3) S.drag.moved = true;
    if (D.kind === 'localize' && S.drag.moved) { select(frameAtX(x)); return; }
    if (D.kind === 'match' && S.drag.moved) {
      S.cx = S.drag.cx - (x - S.drag.x) / (second.width * S.zoom);
      S.cy = S.drag.cy - (y - S.drag.y) / (second.height * S.zoom);
      drawSecond();
    }
  });
  window.addEventListener('mouseup', () => { setTimeout(() => { S.drag = null; }, 0); });
  second.addEventListener('click', (e) => {
    if (S.drag && S.drag.moved) return;
    const r = second.getBoundingClientRect(), x = e.clientX - r.left, y = e.clientY - r.top;
    if (D.kind === 'localize') { select(frameAtX(x)); return; }
    if (D.kind === 'match') {
      const v = matrixView(), q = Math.floor((y - v.oy) / v.sy);
      if (q >= 0 && q < nQuery) select(q);
    }
  });
  second.addEventListener('wheel', (e) => {
    if (D.kind !== 'match') return;
    e.preventDefault();
    const r = second.getBoundingClientRect();
    zoomMatrix(e.deltaY < 0 ? 1.25 : 0.8, e.clientX - r.left, e.clientY - r.top);
  }, { passive: false });

  // ---- the selected frame ----------------------------------------------------------------------------------
  function image(side, row, cls, label, attrs) {
    const src = side && side.thumbs && side.thumbs[row];
    const pic = src ? `<img src="${esc(src)}" alt="${esc(label)}">` : '<div class="missing">no image</div>';
    return `<div class="frame ${cls}" ${attrs || ''}>${pic}${esc(label)}</div>`;
  }
  function renderMatch(q) {
    const positives = D.positives ? new Set(D.positives[q] || []) : null;
    let out = `<h2>Query ${esc(query.names[q])} (row ${q})</h2>` +
      image(query, q, 'query', `query ${query.names[q]}`, `data-query="${q}"`);
    D.methods.forEach((m, i) => {
      const o = i === S.method ? outcome(q) : (m.correct[q] === 1 ? 'right' : (m.correct[q] === 0 ? 'wrong' : 'none'));
      out += `<div class="method" data-method="${i}"><h3>${esc(m.name)}: <span class="outcome-${o}">${o}</span></h3>`;
      m.refs[q].slice(0, SHOWN).forEach((r, k) => {
        if (r < 0) return;
        const truth = positives && positives.has(r);
        const cls = truth ? 'true' : (k === 0 && m.correct[q] === 0 ? 'wrong' : '');
        const d = m.distances[q][k];
        out += image(reference, r, cls, `${reference.names[r]} (${d === null ? '-' : d.toFixed(3)})`,
                     `data-ref="${r}" data-true="${truth ? 1 : 0}"`);
      });
      out += '</div>';
    });
    return out;
  }
  function renderLocalize(q) {
    const st = D.stream, row = st.rows[q];
    let out = `<h2>Frame ${q}: <span class="outcome-${outcome(q)}" id="status">${esc(st.status[q])}</span></h2>`;
    out += image(query, q, 'query', `query ${query.names[q]}`, `data-query="${q}"`);
    const at = st.localised[q] >= 0 ? st.localised[q] : st.best[q];
    if (at >= 0) out += image(reference, at, st.localised[q] >= 0 ? (st.correct[q] === 0 ? 'wrong' : 'true') : '',
                              `${st.localised[q] >= 0 ? 'localised' : 'best'}: ${reference.names[at]}`, `data-ref="${at}"`);
    out += '<table class="kv" id="stream-row">' +
      st.columns.map((c, i) => `<tr><th>${esc(c)}</th><td data-column="${esc(c)}">${esc(row[i])}</td></tr>`).join('') +
      '</table>';
    return out;
  }
  function renderFacts() {
    const f = D.facts, rows = Object.entries(f).filter(([k]) => k !== 'sessions');
    let out = '<h2>Map</h2><table class="kv" id="map-facts">' +
      rows.map(([k, v]) => `<tr><th>${esc(k)}</th><td>${esc(typeof v === 'object' ? JSON.stringify(v) : v)}</td></tr>`).join('') +
      '</table><h2>Sessions</h2><table class="kv" id="sessions"><tr><th>name</th><th>frames</th><th>first row</th><th>added</th></tr>' +
      (f.sessions || []).map((s) => `<tr><td>${esc(s.name)}</td><td>${esc(s.frames)}</td><td>${esc(s.first)}</td><td>${esc(s.added || '')}</td></tr>`).join('') +
      '</table>';
    return out;
  }
  function select(q) {
    if (!nQuery) return;
    S.sel = Math.min(nQuery - 1, Math.max(0, q));
    document.getElementById('selected').innerHTML = D.kind === 'match' ? renderMatch(S.sel) : renderLocalize(S.sel);
    drawRoute();
    drawSecond();
  }
  function step(direction, failuresOnly) {
    for (let q = S.sel + direction; q >= 0 && q < nQuery; q += direction) {
      if (!failuresOnly || isFailure(q)) { select(q); return true; }
    }
    return false;
  }
  window.addEventListener('keydown', (e) => {
    const keys = { ArrowRight: () => step(1, false), ArrowLeft: () => step(-1, false), n: () => step(1, true),
                   p: () => step(-1, true), '+': () => zoomAtSelection(2), '-': () => zoomAtSelection(0.5) };
    if (keys[e.key]) { e.preventDefault(); keys[e.key](); }
  });

  // ---- start -----------------------------------------------------------------------------------------------
  document.getElementById('notes').innerHTML = (D.notes || []).map((n) => `<p>${esc(n)}</p>`).join('');
  const legend = D.kind === 'localize'
    ? [['right', 'localised, right'], ['wrong', 'localised, wrong'], ['lost', 'lost'], ['none', 'other'], ['ref', 'map']]
    : [['right', 'top-1 right'], ['wrong', 'top-1 wrong'], ['none', 'no true match / no window'], ['ref', 'reference']];
  document.getElementById('legend').innerHTML = legend.map(([k, t]) => `<span><i style="background:${C[k]}"></i>${esc(t)}</span>`).join('');
  if (D.kind === 'match' && D.methods.length > 1) {
    const pick = document.createElement('select');
    pick.id = 'method';
    D.methods.forEach((m, i) => { const o = document.createElement('option'); o.value = i; o.textContent = m.name; pick.appendChild(o); });
    pick.addEventListener('change', () => { S.method = Number(pick.value); select(S.sel); });
    document.getElementById('legend').appendChild(pick);
  }
  const titles = { match: 'Distances: each query\'s top-K (rows: queries, columns: references; green band: ground truth)',
                   localize: 'Timeline: score (blue), threshold (orange), status below' };
  document.getElementById('second-title').textContent = titles[D.kind] || '';
  document.getElementById('hint').textContent = D.kind === 'map' ? ''
    : 'Click a frame on the route or below; arrows step, n / p go to the next / previous failure' +
      (D.kind === 'match' ? ', wheel or + / - zoom, drag pans.' : ', drag scrubs.');
  if (D.kind === 'map') {
    second.style.display = 'none';
    document.getElementById('facts').innerHTML = renderFacts();
    drawRoute();
  } else {
    select(0);
  }
  window.seqvprView = { data: D, state: S, select, step, pointOf, matrixPointOf, zoomMatrix, outcome,
                        timelineX, selected: () => S.sel };
})();
