// kinefuse 3-D skeleton viewer (needs the global THREE of _vendor/three/three.min.js).
// Two entry points: kinefuseReport(data) for the recording in an HTML report and
// kinefuseLive(meta) for `kinefuse stream --view` (frames as server-sent events).
// Positions arrive in the data's world frame (z up), m; three.js is y up, so (x, y, z) is
// drawn at (x, z, -y). State for tests and users: window.kfViewer.
(function () {
  "use strict";

  function decodeInt16(b64) {
    var bin = atob(b64), n = bin.length, bytes = new Uint8Array(n);
    for (var i = 0; i < n; i++) bytes[i] = bin.charCodeAt(i);
    return new Int16Array(bytes.buffer);
  }
  function decodeUint8(b64) {
    var bin = atob(b64), n = bin.length, bytes = new Uint8Array(n);
    for (var i = 0; i < n; i++) bytes[i] = bin.charCodeAt(i);
    return bytes;
  }
  function el(tag, attrs, text) {
    var e = document.createElement(tag);
    for (var k in attrs || {}) e.setAttribute(k, attrs[k]);
    if (text !== undefined) e.textContent = text;
    return e;
  }

  // One skeleton: bones (wide line segments) in one colour, joints as points coloured per
  // sample. Missing joints (NaN) and their bones are not drawn.
  var materials = [], viewSize = [800, 500];
  function Skeleton(scene, nJoints, edges, color, lineWidth, pointSize, dashed) {
    this.n = nJoints;
    this.edges = edges;
    this.group = new THREE.Group();
    this.linePos = new Float32Array(Math.max(edges.length, 1) * 6);
    this.geom = new THREE.LineSegmentsGeometry();
    this.mat = new THREE.LineMaterial({ color: color, linewidth: lineWidth, worldUnits: false,
      dashed: !!dashed, dashSize: 0.03, gapSize: 0.02 });
    this.dashed = !!dashed;
    this.mat.resolution.set(viewSize[0], viewSize[1]);
    materials.push(this.mat);
    this.lines = new THREE.LineSegments2(this.geom, this.mat);
    this.lines.frustumCulled = false;
    this.ptPos = new Float32Array(nJoints * 3);
    this.ptCol = new Float32Array(nJoints * 3);
    var pg = new THREE.BufferGeometry();
    pg.setAttribute("position", new THREE.BufferAttribute(this.ptPos, 3).setUsage(THREE.DynamicDrawUsage));
    pg.setAttribute("color", new THREE.BufferAttribute(this.ptCol, 3).setUsage(THREE.DynamicDrawUsage));
    this.points = new THREE.Points(pg, new THREE.PointsMaterial({ size: pointSize, vertexColors: true, sizeAttenuation: false }));
    this.points.frustumCulled = false;
    this.group.add(this.lines);
    this.group.add(this.points);
    this.baseColor = new THREE.Color(color);
    scene.add(this.group);
  }
  var FAR = 1e5;
  // xyz: array-like (J*3) in m (NaN = missing); colors: array of THREE.Color or null.
  Skeleton.prototype.set = function (xyz, colors) {
    for (var j = 0; j < this.n; j++) {
      var x = xyz[3 * j], y = xyz[3 * j + 1], z = xyz[3 * j + 2];
      var ok = isFinite(x) && isFinite(y) && isFinite(z);
      this.ptPos[3 * j] = ok ? x : FAR;
      this.ptPos[3 * j + 1] = ok ? z : FAR;
      this.ptPos[3 * j + 2] = ok ? -y : FAR;
      var c = (colors && colors[j]) || this.baseColor;
      this.ptCol[3 * j] = c.r; this.ptCol[3 * j + 1] = c.g; this.ptCol[3 * j + 2] = c.b;
    }
    var m = 0;
    for (var e = 0; e < this.edges.length; e++) {
      var a = this.edges[e][0], b = this.edges[e][1];
      if (this.ptPos[3 * a] === FAR || this.ptPos[3 * b] === FAR) continue;
      for (var k = 0; k < 3; k++) {
        this.linePos[6 * m + k] = this.ptPos[3 * a + k];
        this.linePos[6 * m + 3 + k] = this.ptPos[3 * b + k];
      }
      m++;
    }
    this.lines.visible = m > 0;
    if (m > 0) {
      this.geom.setPositions(this.linePos.subarray(0, 6 * m));
      if (this.dashed) this.lines.computeLineDistances();
    }
    this.points.geometry.attributes.position.needsUpdate = true;
    this.points.geometry.attributes.color.needsUpdate = true;
  };

  function makeStage(container, center, radius) {
    var canvas = el("canvas", { class: "kf-canvas", "aria-label": "3-D skeleton view" });
    container.appendChild(canvas);
    var renderer;
    try {
      renderer = new THREE.WebGLRenderer({ canvas: canvas, antialias: true, preserveDrawingBuffer: true });
    } catch (err) {  // no WebGL (disabled, or a very old browser): say so, keep the page
      container.replaceChildren(el("p", { class: "note kf-no-webgl" },
        "The 3-D viewer needs WebGL, which this browser does not provide; the figures below " +
        "show the same data."));
      throw err;
    }
    renderer.setPixelRatio(window.devicePixelRatio || 1);
    var scene = new THREE.Scene();
    scene.background = new THREE.Color("#ffffff");
    var camera = new THREE.PerspectiveCamera(40, 1, 0.01, 200);
    var controls = new THREE.OrbitControls(camera, canvas);
    var grid = null;
    // look at center = (x, y, z, floor z) from a fixed direction, radius m around it
    function aim(center, radius) {
      var c = new THREE.Vector3(center[0], center[2], -center[1]);
      camera.position.set(c.x + 2.0 * radius, c.y + 0.9 * radius, c.z + 2.8 * radius);
      controls.target.copy(c);
      controls.update();
      if (grid) scene.remove(grid);
      grid = new THREE.GridHelper(Math.max(4 * radius, 1), 20, 0xb8bfcc, 0xe3e6ec);
      grid.position.set(c.x, center[3], c.z);
      scene.add(grid);
    }
    aim(center, radius);
    function resize() {
      var w = Math.max(container.clientWidth - 4, 200), h = Math.round(Math.min(w * 0.62, 560));
      renderer.setSize(w, h, true);
      viewSize = [w, h];
      materials.forEach(function (m) { m.resolution.set(w, h); });
      camera.aspect = w / h;
      camera.updateProjectionMatrix();
    }
    resize();
    var onResize = [];
    var lastW = container.clientWidth;
    function refit() {
      if (container.clientWidth === lastW) return;
      lastW = container.clientWidth;
      resize();
      onResize.forEach(function (f) { f(); });
    }
    if (window.ResizeObserver) new ResizeObserver(refit).observe(container);
    else window.addEventListener("resize", refit);
    return { canvas: canvas, renderer: renderer, scene: scene, camera: camera, controls: controls, aim: aim, onResize: onResize };
  }

  function legendRow(list, color, label, shape) {
    var li = el("li");
    var sw = el("span", { class: "kf-swatch kf-" + shape });
    sw.style.background = color;
    li.appendChild(sw);
    li.appendChild(document.createTextNode(" " + label));
    list.appendChild(li);
  }

  function sourceColors(data) {
    var out = {};
    for (var code in data.source_colors) out[code] = new THREE.Color(data.source_colors[code]);
    return out;
  }

  function sourceLegend(box, data) {
    var ul = el("ul", { class: "kf-legend" });
    ul.appendChild(el("li", { class: "kf-legend-title" }, "joint colour = source:"));
    for (var code in data.source_names) legendRow(ul, data.source_colors[code], data.source_names[code], "dot");
    box.appendChild(ul);
  }

  // ---------------------------------------------------------------- report (whole recording)
  window.kinefuseReport = function (data) {
    try { report(data); } catch (err) { console.warn("kinefuse viewer: " + err); }
  };
  function report(data) {
    var root = document.getElementById("kf-viewer");
    var stageBox = root.querySelector(".kf-stage"), side = root.querySelector(".kf-side");
    var J = data.joints.length, F = data.t.length;
    var stage = makeStage(stageBox, data.center, data.radius);
    var srcCol = sourceColors(data);
    var series = data.series.map(function (s) {
      var pos = decodeInt16(s.pos);
      var src = s.src ? decodeUint8(s.src) : null;
      var nJ = s.joints ? s.joints.length : J;
      var sk = new Skeleton(stage.scene, nJ, s.edges || data.edges, s.color,
        s.kind === "body" ? 5 : s.kind === "reference" ? 3.5 : 2.5, s.kind === "body" ? 4 : 9, s.dashed);
      return { name: s.name, kind: s.kind, pos: pos, src: src, nJ: nJ, sk: sk, visible: s.visible, color: s.color, dashed: !!s.dashed };
    });
    var state = { frame: 0, playing: false, speed: 1, framesDrawn: 0, visible: {},
      series: series.map(function (s) { return { name: s.name, kind: s.kind, color: s.color }; }) };
    window.kfViewer = state;
    var ref = series.filter(function (s) { return s.kind === "reference"; })[0] || null;

    var bar = root.querySelector(".kf-controls");
    var play = el("button", { id: "kf-play", type: "button" }, "▶ play");
    var slider = el("input", { id: "kf-time", type: "range", min: "0", max: String(F - 1), value: "0", step: "1" });
    var label = el("span", { id: "kf-time-label", class: "kf-time" });
    var speed = el("select", { id: "kf-speed", title: "playback speed" });
    [0.25, 0.5, 1, 2, 4].forEach(function (v) {
      var o = el("option", { value: String(v) }, v + "×");
      if (v === 1) o.selected = true;
      speed.appendChild(o);
    });
    bar.appendChild(play); bar.appendChild(slider); bar.appendChild(label); bar.appendChild(speed);

    var toggles = el("ul", { class: "kf-legend" });
    toggles.appendChild(el("li", { class: "kf-legend-title" }, "show (bone colour):"));
    series.forEach(function (s, i) {
      var li = el("li");
      var cb = el("input", { type: "checkbox", class: "kf-toggle", "data-series": s.name, id: "kf-toggle-" + i });
      cb.checked = !!s.visible;
      state.visible[s.name] = cb.checked;
      cb.addEventListener("change", function () { state.visible[s.name] = cb.checked; draw(); });
      var lab = el("label", { for: "kf-toggle-" + i });
      var sw = el("span", { class: "kf-swatch kf-line" });
      sw.style.background = s.dashed
        ? "repeating-linear-gradient(90deg," + s.color + " 0 5px,transparent 5px 8px)" : s.color;
      lab.appendChild(sw);
      lab.appendChild(document.createTextNode(" " + s.name));
      li.appendChild(cb); li.appendChild(lab);
      toggles.appendChild(li);
    });
    side.appendChild(toggles);
    sourceLegend(side, data);
    var errBox = el("div", { class: "kf-errors" });
    side.appendChild(errBox);

    var cur = new Float32Array(3 * Math.max.apply(null, series.map(function (s) { return s.nJ; })));
    function frameXYZ(s, f) {
      var base = f * s.nJ * 3;
      for (var k = 0; k < s.nJ * 3; k++) {
        var v = s.pos[base + k];
        cur[k] = v === -32768 ? NaN : v * data.scale_m;
      }
      return cur;
    }
    function errorsTable(f) {
      if (!ref) { errBox.textContent = ""; return; }
      var shown = series.filter(function (s) { return (s.kind === "method" || s.kind === "camera") && state.visible[s.name]; });
      var tab = el("table", { class: "results kf-err-table" });
      tab.appendChild(el("caption", {}, "error now (cm)"));
      var hr = el("tr");
      hr.appendChild(el("th", {}, "joint"));
      shown.forEach(function (s) { hr.appendChild(el("th", { class: "num" }, s.name)); });
      tab.appendChild(hr);
      for (var j = 0; j < J; j++) {
        var tr = el("tr");
        tr.appendChild(el("td", {}, data.joints[j]));
        var rb = (f * J + j) * 3;
        shown.forEach(function (s) {
          var sb = (f * J + j) * 3, d2 = 0, bad = false;
          for (var k = 0; k < 3; k++) {
            var a = s.pos[sb + k], b = ref.pos[rb + k];
            if (a === -32768 || b === -32768) bad = true;
            d2 += Math.pow((a - b) * data.scale_m, 2);
          }
          tr.appendChild(el("td", { class: "num" }, bad ? "–" : (100 * Math.sqrt(d2)).toFixed(1)));
        });
        tab.appendChild(tr);
      }
      errBox.replaceChildren(tab);
      if (!shown.length) errBox.appendChild(el("p", { class: "note" }, "tick a method to see its errors"));
    }
    function draw() {
      var f = state.frame;
      series.forEach(function (s) {
        s.sk.group.visible = !!state.visible[s.name];
        if (!s.sk.group.visible) return;
        var cols = null;
        if (s.src) {
          cols = [];
          for (var j = 0; j < s.nJ; j++) cols.push(srcCol[s.src[f * s.nJ + j]] || null);
        }
        s.sk.set(frameXYZ(s, f), cols);
      });
      stage.renderer.render(stage.scene, stage.camera);
      state.framesDrawn++;
      slider.value = String(f);
      label.textContent = "t = " + data.t[f].toFixed(2) + " s";
      state.time_s = data.t[f];
      errorsTable(f);
    }
    state.draw = draw;
    var t0 = null, f0 = 0;
    function tick(now) {
      if (!state.playing) return;
      if (t0 === null) { t0 = now; f0 = state.frame; }
      var elapsed = (now - t0) / 1000 * state.speed;
      var target = data.t[f0] + elapsed, f = state.frame;
      while (f < F - 1 && data.t[f + 1] <= target) f++;
      if (f >= F - 1 && data.t[F - 1] <= target) { f = 0; t0 = now; f0 = 0; }
      if (f !== state.frame) { state.frame = f; draw(); }
      requestAnimationFrame(tick);
    }
    function setPlaying(p) {
      state.playing = p;
      play.textContent = p ? "❚❚ pause" : "▶ play";
      t0 = null;
      if (p) requestAnimationFrame(tick);
    }
    play.addEventListener("click", function () { setPlaying(!state.playing); });
    slider.addEventListener("input", function () { state.frame = +slider.value; t0 = null; draw(); });
    speed.addEventListener("change", function () { state.speed = +speed.value; t0 = null; });
    stage.controls.addEventListener("change", function () { stage.renderer.render(stage.scene, stage.camera); });
    stage.onResize.push(draw);
    draw();
    state.ready = true;
  }

  // ---------------------------------------------------------------- live (kinefuse stream --view)
  window.kinefuseLive = function (meta) {
    var root = document.getElementById("kf-viewer");
    var stageBox = root.querySelector(".kf-stage"), side = root.querySelector(".kf-side");
    var J = meta.joints.length;
    var stage = makeStage(stageBox, meta.center, meta.radius);
    var srcCol = sourceColors(meta);
    var sk = new Skeleton(stage.scene, J, meta.edges, meta.color, 3, 11);
    var state = { frames: 0, last: null, connected: false, framesDrawn: 0 };
    window.kfViewer = state;
    var info = el("div", { class: "kf-live-info" });
    var count = el("span", { id: "kf-frames" }, "0");
    var lat = el("span", { id: "kf-latency" }, "–");
    var tnow = el("span", { id: "kf-stream-time" }, "–");
    var conn = el("span", { id: "kf-connection" }, "connecting…");
    [["frames received: ", count], [" · stream time: ", tnow], [" · latency: ", lat], [" · ", conn]].forEach(function (p) {
      info.appendChild(document.createTextNode(p[0])); info.appendChild(p[1]);
    });
    root.querySelector(".kf-controls").appendChild(info);
    sourceLegend(side, meta);
    var tab = el("table", { class: "results", id: "kf-joint-sources" });
    tab.appendChild(el("caption", {}, "source per joint"));
    var cells = meta.joints.map(function (name) {
      var tr = el("tr"); tr.appendChild(el("td", {}, name));
      var td = el("td", {}, "–"); tr.appendChild(td); tab.appendChild(tr);
      return td;
    });
    side.appendChild(tab);
    var angJ = meta.angle_joints || [], angCells = [];
    if (angJ.length) {  // kinefuse stream --chain with segment frames: joint angles live
      var at = el("table", { class: "results", id: "kf-joint-angles" });
      at.appendChild(el("caption", {}, "joint angles (deg, ISB)"));
      var hr = el("tr");
      ["joint", "flexion", "adduction", "int. rotation"].forEach(function (h) { hr.appendChild(el("th", {}, h)); });
      at.appendChild(hr);
      angJ.forEach(function (name) {
        // the trunk's three angles are flexion, lateral bending (right +), axial rotation (left +)
        var tr = el("tr"); tr.appendChild(el("td", {}, name === "trunk" ? "trunk (flex., lat. bend R+, axial rot. L+)" : name));
        var row = [0, 1, 2].map(function () { var td = el("td", {}, "–"); tr.appendChild(td); return td; });
        at.appendChild(tr); angCells.push(row);
      });
      side.appendChild(at);
    }
    var pending = null;
    function render() {
      if (!pending) return;
      var m = pending; pending = null;
      var cols = m.src.map(function (c) { return srcCol[c] || null; });
      sk.set(m.pos.map(function (v) { return v === null ? NaN : v; }), cols);
      stage.renderer.render(stage.scene, stage.camera);
      state.framesDrawn++;
      tnow.textContent = m.t_s.toFixed(2) + " s";
      lat.textContent = m.latency_ms === null ? "–" : m.latency_ms.toFixed(2) + " ms (p50 " + m.latency_p50_ms.toFixed(2) + " ms)";
      for (var j = 0; j < J; j++) {
        var c = m.src[j];
        cells[j].textContent = meta.source_names[c] || "–";
        cells[j].style.color = meta.source_colors[c] || "";
      }
      if (m.ang) {
        for (var a = 0; a < angCells.length; a++) {
          for (var k = 0; k < 3; k++) {
            var v = m.ang[3 * a + k];
            angCells[a][k].textContent = v === null ? "–" : v.toFixed(1);
          }
        }
      }
    }
    stage.controls.addEventListener("change", function () { stage.renderer.render(stage.scene, stage.camera); });
    stage.renderer.render(stage.scene, stage.camera);
    stage.onResize.push(function () { stage.renderer.render(stage.scene, stage.camera); });
    var es = new EventSource(meta.events_url);
    es.onopen = function () { state.connected = true; conn.textContent = "connected"; };
    es.onerror = function () { state.connected = false; conn.textContent = "stream ended or unreachable (retrying)"; };
    var aimed = !meta.auto_aim;
    es.onmessage = function (ev) {
      var m = JSON.parse(ev.data);
      if (!aimed) {  // the page opened before any frame: frame the body once it is seen
        var lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
        for (var i = 0; i < m.pos.length; i++) {
          var v = m.pos[i];
          if (v === null) continue;
          lo[i % 3] = Math.min(lo[i % 3], v); hi[i % 3] = Math.max(hi[i % 3], v);
        }
        if (isFinite(lo[0])) {
          var r = Math.max(0.6, 0.5 * Math.max(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]));
          stage.aim([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, (lo[2] + hi[2]) / 2, lo[2]], r);
          aimed = true;
        }
      }
      state.frames++;
      state.last = m;
      count.textContent = String(state.frames);
      if (!pending) requestAnimationFrame(render);
      pending = m;
    };
    state.ready = true;
  };
})();
