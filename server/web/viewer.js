// crowdmap's map viewer: landmarks and their 95% error ellipses, drawn in metres on a canvas over
// a Leaflet map, from mapd's /api/ endpoints; polls the map version for live updates.
'use strict';
(function () {
  const kEarthRadiusM = 6378137;  // Leaflet's spherical Mercator (EPSG:3857)
  const kChi2Dof2P95 = 5.991464547107979;  // chi-square quantile, 2 dof, p = 0.95
  const kWorld = '-180,-85,180,85';
  const kPollMs = 2000;
  const kScales = {
    sigma: {
      title: 'largest sigma',
      limits: [0.1, 0.2, 0.5, 1, 2, Infinity],
      labels: ['< 0.1 m', '0.1-0.2 m', '0.2-0.5 m', '0.5-1 m', '1-2 m', '> 2 m'],
      value: (l) => l.sigma,
    },
    age: {
      title: 'last seen',
      limits: [60, 3600, 86400, 7 * 86400, 30 * 86400, Infinity],
      labels: ['< 1 min', '< 1 hour', '< 1 day', '< 1 week', '< 30 days', 'older'],
      value: (l) => (Date.now() - l.lastSeen) / 1000,
    },
  };
  const kColours = ['#1a9641', '#66bd63', '#a6a600', '#f08c00', '#e8590c', '#c92a2a'];

  // State, read by the browser test (tests/viewer/viewer_browser_test.py).
  const viewer = (window.crowdmapViewer = {
    ready: false,
    landmarks: new Map(),  // id -> landmark
    version: -1,           // map version of the landmarks held
    drawn: 0,              // ellipses drawn at the last draw (those that reach into the view)
    draws: 0,
    lastDrawMs: 0,         // duration of the last draw
    firstDrawMs: null,     // from navigation start to the end of the first draw with data
    polls: 0,
    selected: null,
    colourBy: 'sigma',
    config: null,
    info: null,
    error: null,
  });

  const $ = (id) => document.getElementById(id);

  function token() {
    return sessionStorage.getItem('crowdmap-token') || '';
  }

  async function getJson(path) {
    const headers = {};
    if (token()) headers.Authorization = 'Bearer ' + token();
    const response = await fetch(path, { headers, cache: 'no-store' });
    const body = await response.json().catch(() => ({}));
    if (!response.ok) {
      const error = new Error(body.error || response.statusText);
      error.status = response.status;
      throw error;
    }
    return { body, headers: response.headers };
  }

  function fromFeature(f) {
    const p = f.properties;
    return {
      id: p.id,
      lon: f.geometry.coordinates[0],
      lat: f.geometry.coordinates[1],
      a: p.ellipse95_semi_major_m,
      b: p.ellipse95_semi_minor_m,
      azimuthDeg: p.ellipse95_azimuth_deg,
      sigma: p.ellipse95_semi_major_m / Math.sqrt(kChi2Dof2P95),  // along the major axis
      sigmaEast: p.sigma_east_m,
      sigmaNorth: p.sigma_north_m,
      version: p.version,
      passages: p.passages_seen,
      lastSeen: p.last_seen_unix_ms,
    };
  }

  function merge(features) {
    for (const f of features) {
      if (f.properties.kind !== 'landmark') continue;
      const l = fromFeature(f);
      viewer.landmarks.set(l.id, l);
    }
  }

  // ----- the map and the ellipse canvas -----
  const map = L.map('map', {
    zoomAnimation: false,
    fadeAnimation: false,
    markerZoomAnimation: false,
    minZoom: 1,
    maxZoom: 24,
    attributionControl: false,
  }).setView([0, 0], 2);
  L.control.scale({ imperial: false, maxWidth: 160 }).addTo(map);
  viewer.map = map;

  const canvas = document.createElement('canvas');
  canvas.className = 'crowdmap-ellipses';
  map.getContainer().appendChild(canvas);
  viewer.canvas = canvas;

  function resizeCanvas() {
    const size = map.getSize();
    const dpr = window.devicePixelRatio || 1;
    canvas.width = Math.round(size.x * dpr);
    canvas.height = Math.round(size.y * dpr);
    canvas.style.width = size.x + 'px';
    canvas.style.height = size.y + 'px';
  }

  function bucket(l) {
    const scale = kScales[viewer.colourBy];
    const v = scale.value(l);
    let i = 0;
    while (v >= scale.limits[i] && i < scale.limits.length - 1) ++i;
    return i;
  }

  // Pixels per metre on the ground at latitude `latDeg` and the map's zoom (Web Mercator).
  function pixelsPerMetre(latDeg) {
    return (256 * Math.pow(2, map.getZoom())) / (2 * Math.PI * kEarthRadiusM * Math.cos((latDeg * Math.PI) / 180));
  }

  // The ellipse of `l` in container pixels: centre, semi-axes and rotation (clockwise from +x).
  function screenEllipse(l) {
    const p = map.latLngToContainerPoint([l.lat, l.lon]);
    const k = pixelsPerMetre(l.lat);
    return { x: p.x, y: p.y, rx: l.a * k, ry: l.b * k, rotation: ((l.azimuthDeg - 90) * Math.PI) / 180 };
  }

  function draw() {
    const t0 = performance.now();
    const size = map.getSize();
    const dpr = window.devicePixelRatio || 1;
    if (canvas.width !== Math.round(size.x * dpr) || canvas.height !== Math.round(size.y * dpr)) resizeCanvas();
    const ctx = canvas.getContext('2d');
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    ctx.clearRect(0, 0, size.x, size.y);
    const bounds = map.getBounds().pad(0.5);
    const south = bounds.getSouth(), north = bounds.getNorth(), west = bounds.getWest(), east = bounds.getEast();
    const outlines = kColours.map(() => new Path2D());
    const dots = kColours.map(() => new Path2D());
    let drawn = 0;
    let selected = null;
    for (const l of viewer.landmarks.values()) {
      if (l.lat < south || l.lat > north || l.lon < west || l.lon > east) continue;
      const e = screenEllipse(l);
      if (e.x + e.rx < 0 || e.x - e.rx > size.x || e.y + e.rx < 0 || e.y - e.rx > size.y) continue;
      const i = bucket(l);
      const rx = Math.max(e.rx, 0.5), ry = Math.max(e.ry, 0.5);
      if (rx < 2) {
        // An ellipse under 2 px would vanish under the dot that shows it (a 4 px square: far cheaper
        // to draw than an arc, which matters with thousands of landmarks in view).
        dots[i].rect(e.x - 2, e.y - 2, 4, 4);
      } else {
        outlines[i].moveTo(e.x + rx * Math.cos(e.rotation), e.y + rx * Math.sin(e.rotation));
        outlines[i].ellipse(e.x, e.y, rx, ry, e.rotation, 0, 2 * Math.PI);
        // An ellipse a few pixels wide is still shown, by a dot at its centre.
        if (rx < 3) {
          dots[i].moveTo(e.x + 2, e.y);
          dots[i].arc(e.x, e.y, 2, 0, 2 * Math.PI);
        }
      }
      if (l.id === viewer.selected) selected = { e, rx, ry };
      ++drawn;
    }
    ctx.lineWidth = 2;
    kColours.forEach((colour, i) => {
      ctx.strokeStyle = colour;
      ctx.stroke(outlines[i]);
      ctx.fillStyle = colour;
      ctx.fill(dots[i]);
    });
    if (selected !== null) {
      ctx.lineWidth = 3;
      ctx.strokeStyle = '#000';
      ctx.beginPath();
      ctx.ellipse(selected.e.x, selected.e.y, selected.rx + 4, selected.ry + 4, selected.e.rotation, 0, 2 * Math.PI);
      ctx.stroke();
    }
    viewer.drawn = drawn;
    viewer.lastDrawMs = performance.now() - t0;
    ++viewer.draws;
  }

  let drawPending = false;
  function scheduleDraw() {
    if (drawPending) return;
    drawPending = true;
    requestAnimationFrame(() => {
      drawPending = false;
      draw();
    });
  }
  map.on('move zoom viewreset resize', scheduleDraw);
  map.on('moveend', () => {
    const c = map.getCenter();
    history.replaceState(null, '', `#${c.lat.toFixed(6)},${c.lng.toFixed(6)},${map.getZoom()}`);
  });

  // ----- panel -----
  function renderLegend() {
    const scale = kScales[viewer.colourBy];
    $('legend').innerHTML = '';
    const title = document.createElement('div');
    title.textContent = scale.title + ':';
    $('legend').appendChild(title);
    scale.labels.forEach((label, i) => {
      const row = document.createElement('div');
      const swatch = document.createElement('span');
      swatch.className = 'swatch';
      swatch.style.borderColor = kColours[i];
      row.appendChild(swatch);
      row.appendChild(document.createTextNode(label));
      $('legend').appendChild(row);
    });
  }

  function setStatus(text, isError) {
    $('status').textContent = text;
    $('status').className = isError ? 'error' : '';
  }

  function showError(error) {
    viewer.error = error.message;
    if (error.status === 401) {
      $('token-box').hidden = false;
      setStatus('authentication is on: enter a bearer token (' + error.message + ')', true);
    } else {
      setStatus('error: ' + error.message, true);
    }
  }

  function statusLine() {
    const info = viewer.info || {};
    const truncated = viewer.truncated ? ` (cut at ${viewer.truncated})` : '';
    setStatus(
      `map version ${viewer.version}, ${viewer.landmarks.size} landmarks${truncated}, ` +
        `${Number(info.queue_depth || 0)} passages queued; updated ${new Date().toLocaleTimeString()}`,
      false,
    );
  }

  function row(table, name, value) {
    const tr = table.insertRow();
    tr.insertCell().textContent = name;
    tr.insertCell().textContent = value;
  }

  function renderDetails() {
    const l = viewer.landmarks.get(viewer.selected);
    const box = $('details');
    box.innerHTML = '';
    if (l === undefined) {
      box.textContent = 'Click a landmark.';
      return;
    }
    const table = document.createElement('table');
    table.id = 'details-table';
    row(table, 'id', String(l.id));
    row(table, 'sigma', `${l.sigma.toFixed(3)} m (major axis)`);
    row(table, 'sigma E / N', `${l.sigmaEast.toFixed(3)} / ${l.sigmaNorth.toFixed(3)} m`);
    row(table, '95% ellipse', `${l.a.toFixed(3)} x ${l.b.toFixed(3)} m, azimuth ${l.azimuthDeg.toFixed(1)} deg`);
    row(table, 'passages seen', String(l.passages));
    row(table, 'last seen', l.lastSeen > 0 ? new Date(l.lastSeen).toISOString() : 'never');
    row(table, 'version', String(l.version));
    row(table, 'position', `${l.lat.toFixed(7)}, ${l.lon.toFixed(7)}`);
    box.appendChild(table);
  }

  // The landmark whose ellipse contains the click, or the nearest centre within 8 px.
  map.on('click', (event) => {
    const click = event.containerPoint;
    let best = null;
    let bestScore = Infinity;
    for (const l of viewer.landmarks.values()) {
      const e = screenEllipse(l);
      const dx = click.x - e.x, dy = click.y - e.y;
      const distance = Math.hypot(dx, dy);
      if (distance > Math.max(8, e.rx)) continue;
      const c = Math.cos(e.rotation), s = Math.sin(e.rotation);
      const u = (dx * c + dy * s) / Math.max(e.rx, 1e-9), v = (-dx * s + dy * c) / Math.max(e.ry, 1e-9);
      const inside = u * u + v * v <= 1;
      if (!inside && distance > 8) continue;
      const score = inside ? distance - 1e6 : distance;
      if (score < bestScore) {
        bestScore = score;
        best = l;
      }
    }
    viewer.selected = best === null ? null : best.id;
    renderDetails();
    scheduleDraw();
  });

  async function loadQuarantined() {
    const box = $('quarantined');
    try {
      const list = (await getJson('api/passages?state=quarantined')).body.passages || [];
      box.innerHTML = '';
      if (list.length === 0) {
        box.textContent = 'none';
        return;
      }
      const ul = document.createElement('ul');
      for (const p of list) {
        const li = document.createElement('li');
        li.textContent = `#${p.id} ${p.vehicle_id}/${p.passage_id}: ${p.error}`;
        ul.appendChild(li);
      }
      box.appendChild(ul);
    } catch (error) {
      box.textContent = error.status === 403 ? 'needs role operator' : 'error: ' + error.message;
    }
  }

  // ----- data -----
  async function loadAll() {
    const response = await getJson('api/landmarks?bbox=' + kWorld);
    viewer.landmarks.clear();
    merge(response.body.features);
    viewer.version = response.body.map_version;
    viewer.truncated = response.headers.get('X-Truncated');
  }

  function viewFromHash() {
    const parts = location.hash.slice(1).split(',').map(Number);
    if (parts.length !== 3 || parts.some((x) => !Number.isFinite(x))) return false;
    map.setView([parts[0], parts[1]], parts[2]);
    return true;
  }

  function fitToLandmarks() {
    if (viewer.landmarks.size === 0) return;
    let south = 90, north = -90, west = 180, east = -180;
    for (const l of viewer.landmarks.values()) {
      south = Math.min(south, l.lat);
      north = Math.max(north, l.lat);
      west = Math.min(west, l.lon);
      east = Math.max(east, l.lon);
    }
    map.fitBounds([[south, west], [north, east]], { padding: [30, 30], maxZoom: 19 });
  }

  let polling = false;
  async function poll() {
    if (!viewer.ready) {
      setTimeout(poll, kPollMs);
      return;
    }
    try {
      viewer.info = (await getJson('api/info')).body;
      const version = Number(viewer.info.map_version);
      if (version !== viewer.version) {
        const changed = await getJson(`api/landmarks?bbox=${kWorld}&since_version=${viewer.version}`);
        merge(changed.body.features);
        // Landmarks taken out of the map (an excluded passage's); servers that predate the list
        // leave them out, and then the whole map is read again.
        for (const id of changed.body.removed_ids || []) viewer.landmarks.delete(Number(id));
        viewer.version = changed.body.map_version;
        if (Number(viewer.info.landmark_count) !== viewer.landmarks.size) await loadAll();
        if (viewer.selected !== null) renderDetails();
        scheduleDraw();
      }
      if (Number(viewer.info.passages_quarantined || 0) !== viewer.quarantinedCount) {
        viewer.quarantinedCount = Number(viewer.info.passages_quarantined || 0);
        await loadQuarantined();
      }
      viewer.error = null;
      statusLine();
    } catch (error) {
      showError(error);
    }
    ++viewer.polls;
    setTimeout(poll, kPollMs);
  }

  async function start() {
    try {
      viewer.config = (await getJson('api/config')).body;
      if (viewer.config.basemap_url) {
        L.tileLayer(viewer.config.basemap_url, { maxZoom: 24, maxNativeZoom: 19 }).addTo(map);
      }
      if (viewer.config.auth) $('token-box').hidden = false;
      viewer.info = (await getJson('api/info')).body;
      await loadAll();
      if (!viewFromHash()) fitToLandmarks();
      resizeCanvas();
      draw();
      viewer.firstDrawMs = performance.now();
      viewer.quarantinedCount = Number(viewer.info.passages_quarantined || 0);
      await loadQuarantined();
      statusLine();
      viewer.ready = true;
    } catch (error) {
      showError(error);
    }
    if (!polling) {
      polling = true;
      setTimeout(poll, kPollMs);
    }
  }

  $('colour-by').addEventListener('change', (event) => {
    viewer.colourBy = event.target.value;
    renderLegend();
    scheduleDraw();
  });
  $('token-save').addEventListener('click', () => {
    sessionStorage.setItem('crowdmap-token', $('token').value.trim());
    $('token').value = '';
    start();
  });
  renderLegend();
  start();
})();
