// mapsqueeze view: a small WebGL 1 point renderer (gl.POINTS from uint16 position buffers), an orbit camera with
// mouse and touch, colour ramps drawn both on the points and on a colour-bar canvas. The data comes from the JSON
// block "scene-data" of this page (see mapsqueeze/view/scene.py); nothing is fetched.
"use strict";
(function () {
  window.addEventListener("error", (e) => {
    document.getElementById("message").textContent = `viewer error: ${e.message}`;
  });
  const scene = JSON.parse(document.getElementById("scene-data").textContent);
  const CLOUD_COLORS = { original: [0.3, 0.64, 1.0], decoded: [1.0, 0.55, 0.1] };
  const EMBEDDING_COLOR = [1.0, 0.2, 0.9];
  const MODE_COLORS = [[0.35, 0.9, 0.45], [1.0, 0.85, 0.2], [0.95, 0.35, 0.35], [0.6, 0.6, 1.0], [0.8, 0.8, 0.8]];
  const RAMPS = {
    height: [[0, [0.27, 0.0, 0.33]], [0.25, [0.23, 0.32, 0.55]], [0.5, [0.13, 0.57, 0.55]],
      [0.75, [0.37, 0.79, 0.38]], [1, [0.99, 0.91, 0.14]]],
    error: [[0, [0.15, 0.3, 1.0]], [0.25, [0.1, 0.85, 0.9]], [0.5, [0.3, 0.9, 0.3]], [0.75, [1.0, 0.9, 0.1]],
      [1, [0.95, 0.15, 0.1]]],
    intensity: [[0, [0.12, 0.12, 0.12]], [1, [1.0, 1.0, 1.0]]],
  };
  const FOV = 50 * Math.PI / 180;
  const $ = (id) => document.getElementById(id);
  const fmt = (v, digits) => v === null || v === undefined ? "-" : Number(v).toFixed(digits);
  const count = (v) => v === null || v === undefined ? "-" : Number(v).toLocaleString("en-US");

  function decode(b64, Type) {
    const bin = atob(b64);
    const bytes = new Uint8Array(bin.length);
    for (let i = 0; i < bin.length; i++) bytes[i] = bin.charCodeAt(i);
    return new Type(bytes.buffer);
  }

  function rampColor(ramp, t) {
    t = Math.min(Math.max(t, 0), 1);
    for (let i = 1; i < ramp.length; i++) {
      if (t <= ramp[i][0]) {
        const [t0, c0] = ramp[i - 1], [t1, c1] = ramp[i];
        const f = (t - t0) / Math.max(t1 - t0, 1e-9);
        return c0.map((c, k) => c + f * (c1[k] - c));
      }
    }
    return ramp[ramp.length - 1][1];
  }

  // ---- state, from the defaults and the URL fragment (#color=error&layout=side&tiles=1&embedding=1&size=3&view=top)
  const hasError = scene.clouds.some((c) => c.error !== null);
  const hasIntensity = scene.intensityRange !== null;
  const state = {
    color: "cloud", layout: "overlay", show: { original: true, decoded: true }, tiles: false, embedding: false,
    pointSize: 2, detail: 1000, movingBudget: 300000, errorMax: scene.errorDefault || scene.errorMax || 1,
    highlight: -1, view: "orbit",
  };
  const hash = new URLSearchParams(location.hash.slice(1));
  if (hash.has("color")) state.color = hash.get("color");
  if (hash.has("layout")) state.layout = hash.get("layout");
  for (const name of ["original", "decoded"]) if (hash.has(name)) state.show[name] = hash.get(name) !== "0";
  if (hash.has("tiles")) state.tiles = hash.get("tiles") !== "0";
  if (hash.has("embedding")) state.embedding = hash.get("embedding") !== "0";
  if (hash.has("size")) state.pointSize = Number(hash.get("size")) || 2;
  if (hash.has("errormax")) state.errorMax = Number(hash.get("errormax")) || state.errorMax;
  if (hash.has("view")) state.view = hash.get("view");
  if ((state.color === "error" && !hasError) || (state.color === "intensity" && !hasIntensity)) state.color = "cloud";

  // ---- WebGL set-up
  const canvas = $("gl");
  const gl = canvas.getContext("webgl", { antialias: false, preserveDrawingBuffer: true });
  if (!gl) {
    $("message").textContent = "WebGL is not available in this browser: the points cannot be drawn.";
  }

  function program(vertexSource, fragmentSource) {
    const build = (type, source) => {
      const shader = gl.createShader(type);
      gl.shaderSource(shader, source);
      gl.compileShader(shader);
      if (!gl.getShaderParameter(shader, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(shader));
      return shader;
    };
    const p = gl.createProgram();
    gl.attachShader(p, build(gl.VERTEX_SHADER, vertexSource));
    gl.attachShader(p, build(gl.FRAGMENT_SHADER, fragmentSource));
    gl.bindAttribLocation(p, 0, "a_pos");
    gl.linkProgram(p);
    if (!gl.getProgramParameter(p, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(p));
    const info = { program: p, attributes: {}, uniforms: {} };
    for (let i = 0; i < gl.getProgramParameter(p, gl.ACTIVE_ATTRIBUTES); i++) {
      const a = gl.getActiveAttrib(p, i);
      info.attributes[a.name] = gl.getAttribLocation(p, a.name);
    }
    for (let i = 0; i < gl.getProgramParameter(p, gl.ACTIVE_UNIFORMS); i++) {
      const u = gl.getActiveUniform(p, i);
      info.uniforms[u.name] = gl.getUniformLocation(p, u.name);
    }
    return info;
  }

  const POINT_VS = `
    attribute vec3 a_pos; attribute float a_value;
    uniform mat4 u_mvp; uniform vec3 u_low; uniform vec3 u_size; uniform float u_pointSize;
    uniform mediump int u_mode; uniform vec2 u_range;
    varying float v_t;
    void main() {
      vec3 p = u_low + a_pos * u_size;
      gl_Position = u_mvp * vec4(p, 1.0);
      gl_PointSize = u_pointSize;
      float raw = u_mode == 1 ? p.z : a_value;
      v_t = clamp((raw - u_range.x) / max(u_range.y - u_range.x, 1e-9), 0.0, 1.0);
    }`;
  const POINT_FS = `
    precision mediump float;
    varying float v_t; uniform mediump int u_mode; uniform vec3 u_color; uniform sampler2D u_ramp; uniform bool u_round;
    void main() {
      vec2 c = gl_PointCoord - 0.5;
      if (u_round && dot(c, c) > 0.25) discard;
      gl_FragColor = u_mode == 0 ? vec4(u_color, 1.0)
                                 : vec4(texture2D(u_ramp, vec2(v_t * 0.99609375 + 0.001953125, 0.5)).rgb, 1.0);
    }`;
  const LINE_VS = `
    attribute vec3 a_pos; attribute vec3 a_color; uniform mat4 u_mvp; varying vec3 v_color;
    void main() { gl_Position = u_mvp * vec4(a_pos, 1.0); v_color = a_color; }`;
  const LINE_FS = `
    precision mediump float; varying vec3 v_color;
    void main() { gl_FragColor = vec4(v_color, 1.0); }`;

  const clouds = scene.clouds.map((c) => ({ ...c, buffers: {} }));
  let pointProgram, lineProgram, rampTextures = {}, embeddingBuffer, tileBuffer, tileVertexCount = 0;

  function uploadBuffer(data) {
    const buffer = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, buffer);
    gl.bufferData(gl.ARRAY_BUFFER, data, gl.STATIC_DRAW);
    return buffer;
  }

  function rampTexture(ramp) {
    const pixels = new Uint8Array(256 * 4);
    for (let i = 0; i < 256; i++) {
      const c = rampColor(ramp, i / 255);
      pixels.set([c[0] * 255, c[1] * 255, c[2] * 255, 255], i * 4);
    }
    const texture = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, texture);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA, 256, 1, 0, gl.RGBA, gl.UNSIGNED_BYTE, pixels);
    for (const p of [gl.TEXTURE_MIN_FILTER, gl.TEXTURE_MAG_FILTER]) gl.texParameteri(gl.TEXTURE_2D, p, gl.LINEAR);
    for (const p of [gl.TEXTURE_WRAP_S, gl.TEXTURE_WRAP_T]) gl.texParameteri(gl.TEXTURE_2D, p, gl.CLAMP_TO_EDGE);
    return texture;
  }

  const modeNames = [...new Set(scene.tiles.map((t) => t.coding))];
  const modeColor = (coding) => MODE_COLORS[modeNames.indexOf(coding) % MODE_COLORS.length];

  function tileLines(highlight) {
    const EDGES = [[0, 1], [2, 3], [4, 5], [6, 7], [0, 2], [1, 3], [4, 6], [5, 7], [0, 4], [1, 5], [2, 6], [3, 7]];
    const data = [];
    scene.tiles.forEach((t, i) => {
      const corner = (k) => [k & 1 ? t.high[0] : t.low[0], k & 2 ? t.high[1] : t.low[1], k & 4 ? t.high[2] : t.low[2]];
      const color = i === highlight ? [1, 1, 1] : modeColor(t.coding);
      for (const [a, b] of EDGES) data.push(...corner(a), ...color, ...corner(b), ...color);
    });
    return new Float32Array(data);
  }

  if (gl) {
    pointProgram = program(POINT_VS, POINT_FS);
    lineProgram = program(LINE_VS, LINE_FS);
    for (const c of clouds) {
      c.buffers.positions = uploadBuffer(decode(c.positions, Uint16Array));
      if (c.error !== null) c.buffers.error = uploadBuffer(decode(c.error, Uint16Array));
      if (c.intensity !== null) c.buffers.intensity = uploadBuffer(decode(c.intensity, Uint16Array));
    }
    embeddingBuffer = uploadBuffer(decode(scene.embedding.positions, Uint16Array));
    for (const name of Object.keys(RAMPS)) rampTextures[name] = rampTexture(RAMPS[name]);
    tileBuffer = uploadBuffer(tileLines(-1));
    tileVertexCount = scene.tiles.length * 24;
  }

  // ---- camera: orbit around a target, z up
  const box = scene.box;
  const centre = box.low.map((l, k) => l + box.size[k] / 2);
  const radius = 0.5 * Math.hypot(...box.size);
  const camera = {};
  function resetCamera(top) {
    camera.target = centre.slice();
    camera.yaw = top ? -Math.PI / 2 : -Math.PI / 3;
    camera.pitch = top ? 89.9 * Math.PI / 180 : 35 * Math.PI / 180;
    camera.zoom = top ? 0.75 : 0.85;  // distance as a fraction of the one that fits the whole box in the pane
  }
  function fitDistance(aspect) {
    const fovX = 2 * Math.atan(Math.tan(FOV / 2) * aspect);
    return radius / Math.sin(Math.min(FOV, fovX) / 2);
  }
  resetCamera(state.view === "top");

  const sub = (a, b) => a.map((v, k) => v - b[k]);
  const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
  const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
  const normalise = (a) => { const n = Math.hypot(...a) || 1; return a.map((v) => v / n); };

  function cameraBasis() {
    camera.distance = fitDistance(camera.aspect || 1) * camera.zoom;
    const cp = Math.cos(camera.pitch), sp = Math.sin(camera.pitch);
    const forward = [-cp * Math.cos(camera.yaw), -cp * Math.sin(camera.yaw), -sp];
    const right = [-Math.sin(camera.yaw), Math.cos(camera.yaw), 0];
    const up = cross(right, forward);
    const eye = sub(camera.target, forward.map((v) => v * camera.distance));
    return { forward, right, up, eye };
  }

  function viewProjection(aspect) {
    camera.aspect = aspect;
    const { forward, right, up, eye } = cameraBasis();
    const near = Math.max(camera.distance * 0.002, 0.01), far = camera.distance + 4 * radius;
    const f = 1 / Math.tan(FOV / 2);
    const view = [right[0], up[0], -forward[0], 0, right[1], up[1], -forward[1], 0, right[2], up[2], -forward[2], 0,
      -dot(right, eye), -dot(up, eye), dot(forward, eye), 1];
    const proj = [f / aspect, 0, 0, 0, 0, f, 0, 0, 0, 0, (far + near) / (near - far), -1, 0, 0,
      2 * far * near / (near - far), 0];
    const out = new Float32Array(16);
    for (let col = 0; col < 4; col++)
      for (let row = 0; row < 4; row++) {
        let s = 0;
        for (let k = 0; k < 4; k++) s += proj[k * 4 + row] * view[col * 4 + k];
        out[col * 4 + row] = s;
      }
    return out;
  }

  // ---- drawing
  let moving = false, movingTimer = null, frameRequested = false;

  function drawnCount(cloud) {
    const low = Math.min(1000, cloud.drawn);
    const f = state.detail / 1000;
    let n = Math.round(Math.exp(Math.log(low) + f * (Math.log(cloud.drawn) - Math.log(low))));
    if (moving && state.movingBudget > 0) n = Math.min(n, state.movingBudget);
    return Math.max(1, Math.min(n, cloud.drawn));
  }

  function colourSettings(cloud) {
    if (state.color === "height") return { mode: 1, range: scene.heightRange, ramp: "height", value: null };
    if (state.color === "error" && cloud.buffers.error)
      return { mode: 2, range: [0, state.errorMax / Math.max(scene.errorMax, 1e-12)], ramp: "error", value: "error" };
    if (state.color === "intensity" && cloud.buffers.intensity)
      return { mode: 2, range: [0, 1], ramp: "intensity", value: "intensity" };
    return { mode: 0, range: [0, 1], ramp: "height", value: null, color: CLOUD_COLORS[cloud.name] || [0.7, 0.7, 0.7] };
  }

  function disableAttributes() {
    for (let i = 0; i < 4; i++) gl.disableVertexAttribArray(i);
  }

  function drawPoints(buffer, valueBuffer, n, settings, size, mvp) {
    const p = pointProgram;
    disableAttributes();
    gl.useProgram(p.program);
    gl.uniformMatrix4fv(p.uniforms.u_mvp, false, mvp);
    gl.uniform3fv(p.uniforms.u_low, box.low);
    gl.uniform3fv(p.uniforms.u_size, box.size);
    gl.uniform1f(p.uniforms.u_pointSize, size * (window.devicePixelRatio || 1));
    gl.uniform1i(p.uniforms.u_mode, settings.mode);
    gl.uniform2fv(p.uniforms.u_range, settings.range);
    gl.uniform3fv(p.uniforms.u_color, settings.color || [1, 1, 1]);
    gl.uniform1i(p.uniforms.u_round, size >= 3 ? 1 : 0);
    gl.activeTexture(gl.TEXTURE0);
    gl.bindTexture(gl.TEXTURE_2D, rampTextures[settings.ramp]);
    gl.uniform1i(p.uniforms.u_ramp, 0);
    gl.bindBuffer(gl.ARRAY_BUFFER, buffer);
    gl.enableVertexAttribArray(p.attributes.a_pos);
    gl.vertexAttribPointer(p.attributes.a_pos, 3, gl.UNSIGNED_SHORT, true, 0, 0);
    if (p.attributes.a_value !== undefined) {
      if (valueBuffer) {
        gl.bindBuffer(gl.ARRAY_BUFFER, valueBuffer);
        gl.enableVertexAttribArray(p.attributes.a_value);
        gl.vertexAttribPointer(p.attributes.a_value, 1, gl.UNSIGNED_SHORT, true, 0, 0);
      } else {
        gl.vertexAttrib1f(p.attributes.a_value, 0);
      }
    }
    gl.drawArrays(gl.POINTS, 0, n);
  }

  function drawTiles(mvp) {
    const p = lineProgram;
    disableAttributes();
    gl.useProgram(p.program);
    gl.uniformMatrix4fv(p.uniforms.u_mvp, false, mvp);
    gl.bindBuffer(gl.ARRAY_BUFFER, tileBuffer);
    gl.enableVertexAttribArray(p.attributes.a_pos);
    gl.vertexAttribPointer(p.attributes.a_pos, 3, gl.FLOAT, false, 24, 0);
    gl.enableVertexAttribArray(p.attributes.a_color);
    gl.vertexAttribPointer(p.attributes.a_color, 3, gl.FLOAT, false, 24, 12);
    gl.drawArrays(gl.LINES, 0, tileVertexCount);
  }

  function drawPane(x, y, w, h, paneClouds) {
    gl.viewport(x, y, w, h);
    gl.scissor(x, y, w, h);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    const mvp = viewProjection(w / Math.max(h, 1));
    gl.enable(gl.DEPTH_TEST);
    for (const c of paneClouds) {
      const settings = colourSettings(c);
      drawPoints(c.buffers.positions, settings.value ? c.buffers[settings.value] : null, drawnCount(c), settings,
        state.pointSize, mvp);
    }
    if (state.tiles) drawTiles(mvp);
    if (state.embedding && scene.embedding.count) {
      gl.disable(gl.DEPTH_TEST);
      drawPoints(embeddingBuffer, null, scene.embedding.count, { mode: 0, range: [0, 1], ramp: "height",
        color: EMBEDDING_COLOR }, Math.max(4, state.pointSize + 3), mvp);
    }
  }

  function draw() {
    frameRequested = false;
    if (!gl) return;
    const dpr = window.devicePixelRatio || 1;
    const w = Math.max(1, Math.round(canvas.clientWidth * dpr)), h = Math.max(1, Math.round(canvas.clientHeight * dpr));
    if (canvas.width !== w || canvas.height !== h) { canvas.width = w; canvas.height = h; }
    gl.clearColor(0.063, 0.075, 0.094, 1);
    gl.enable(gl.SCISSOR_TEST);
    const shown = clouds.filter((c) => state.show[c.name]);
    const side = state.layout === "side" && clouds.length > 1;
    if (side) {
      const half = Math.floor(w / 2);
      drawPane(0, 0, half, h, shown.filter((c) => c.name === clouds[0].name));
      drawPane(half, 0, w - half, h, shown.filter((c) => c.name !== clouds[0].name));
    } else {
      drawPane(0, 0, w, h, shown);
    }
    const counts = clouds.map((c) => `${c.name}: ${count(state.show[c.name] ? drawnCount(c) : 0)}` +
      ` of ${count(c.total)} points drawn`);
    $("label-left").style.display = $("label-right").style.display = side ? "block" : "none";
    $("drawn-count").style.display = side ? "none" : "block";
    $("label-left").textContent = counts[0];
    $("label-right").textContent = counts.length > 1 ? counts[1] : "";
    $("drawn-count").textContent = counts.join(" \u00b7 ");
  }

  function redraw() {
    if (!frameRequested) { frameRequested = true; requestAnimationFrame(draw); }
  }

  function markMoving() {
    moving = true;
    clearTimeout(movingTimer);
    movingTimer = setTimeout(() => { moving = false; redraw(); }, 250);
    redraw();
  }

  // ---- colour bar and panel
  function drawColorBar() {
    const bar = $("colorbar"), ctx = bar.getContext("2d"), ticks = $("colorbar-ticks"), title = $("colorbar-title");
    ticks.innerHTML = "";
    if (state.color === "cloud") {
      bar.style.display = "none";
      title.innerHTML = clouds.map((c) => `<span class="swatch" style="background:rgb(${(CLOUD_COLORS[c.name] ||
        [0.7, 0.7, 0.7]).map((v) => Math.round(v * 255)).join(",")})"></span>${c.name}`).join(" &nbsp; ") +
        (state.embedding ? ` &nbsp; <span class="swatch" style="background:rgb(255,51,230)"></span>embedding` : "");
      return;
    }
    bar.style.display = "block";
    const ramp = RAMPS[state.color];
    const image = ctx.createImageData(bar.width, bar.height);
    for (let x = 0; x < bar.width; x++) {
      const c = rampColor(ramp, x / (bar.width - 1));
      for (let y = 0; y < bar.height; y++) image.data.set([c[0] * 255, c[1] * 255, c[2] * 255, 255], (y * bar.width + x) * 4);
    }
    ctx.putImageData(image, 0, 0);
    let low, high, unit, label;
    if (state.color === "height") {
      [low, high] = scene.heightRange.map((v) => v + scene.centre[2]);
      unit = " m"; label = "height (world z, metres)";
    } else if (state.color === "error") {
      [low, high] = [0, state.errorMax]; unit = " m";
      label = "error: distance to the nearest point of the other cloud (metres)";
    } else {
      [low, high] = scene.intensityRange; unit = ""; label = "intensity";
    }
    const digits = high - low < 0.1 ? 3 : high - low < 10 ? 2 : 1;
    for (let i = 0; i <= 4; i++) {
      const span = document.createElement("span");
      span.style.left = `${i * 25}%`;
      const clipped = i === 4 ? "\u2265 " : i === 0 && state.color === "height" ? "\u2264 " : "";
      span.textContent = `${clipped}${(low + (high - low) * i / 4).toFixed(digits)}${unit}`;
      ticks.appendChild(span);
    }
    title.textContent = label;
  }

  function buildPanel() {
    const s = scene.summary;
    const modeCounts = modeNames.map((m) => `${scene.tiles.filter((t) => t.coding === m).length} ${m}`).join(", ");
    const rows = [
      ["model", `${s.model} (${s.precision})`],
      ["file", `${count(s.fileBytes)} bytes`],
      ["bits per point", fmt(s.bpp, 4) + (s.original === null ? " (of the stored count)" : "")],
      ["points in the map", count(s.points)],
      ["original points", count(s.original)],
      ["decoded points", count(s.decoded)],
      ["D_e", s.dE === null ? "- (give --original)" : `${fmt(s.dE, 4)} m`],
      ["D_perp", s.dPerp === null ? "-" : `${fmt(s.dPerp, 4)} m`],
      ["IoU", fmt(s.iou, 3)],
      ["tiles", `${scene.tiles.length} (${modeCounts})`],
      ["tile size", s.tileSize.map((v) => fmt(v, 0)).join(" x ") + " m"],
      ["embedding points", count(scene.embedding.count)],
    ];
    $("summary").innerHTML = "";
    for (const [name, value] of rows) {
      const tr = $("summary").insertRow();
      tr.insertCell().textContent = name;
      tr.insertCell().textContent = value;
    }
    const modes = [["cloud", "cloud"], ["height", "height"]];
    if (hasIntensity) modes.push(["intensity", "intensity"]);
    if (hasError) modes.push(["error", "error"]);
    $("color-modes").innerHTML = modes.map(([value, text]) =>
      `<label><input type="radio" name="color" value="${value}"${value === state.color ? " checked" : ""}> ${text}</label>`).join(" ");
    $("tile-legend").innerHTML = modeNames.map((m) => `<span class="swatch" style="background:rgb(${modeColor(m)
      .map((v) => Math.round(v * 255)).join(",")})"></span>${m}`).join(" &nbsp; ");
    const table = $("tiles");
    table.innerHTML = "<tr><th>index</th><th>mode</th><th>model</th><th>points</th><th>bytes</th><th>bpp</th>" +
      "<th>emb.</th></tr>";
    scene.tiles.forEach((t, i) => {
      const tr = table.insertRow();
      tr.className = "tile";
      for (const v of [t.index.join(","), t.coding, t.model || "-", count(t.points), count(t.bytes),
        fmt(8 * t.bytes / t.points, 3), count(t.embedding)]) tr.insertCell().textContent = v;
      tr.addEventListener("mouseenter", () => setHighlight(i));
      tr.addEventListener("mouseleave", () => setHighlight(-1));
    });
    if (!hasError) $("error-max-label").style.display = "none";
    $("error-max").value = state.errorMax.toPrecision(3);
    $("error-max").max = (scene.errorMax || 1).toPrecision(4);
    $("point-size").value = state.pointSize;
    $("show-tiles").checked = state.tiles;
    $("show-embedding").checked = state.embedding;
    $("show-original").checked = state.show.original;
    $("show-decoded").checked = state.show.decoded;
    if (clouds.length < 2) $("show-original").parentElement.style.display = "none";
    for (const input of document.querySelectorAll("input[name=layout]")) input.checked = input.value === state.layout;
  }

  function setHighlight(i) {
    state.highlight = i;
    if (gl) {
      gl.bindBuffer(gl.ARRAY_BUFFER, tileBuffer);
      gl.bufferData(gl.ARRAY_BUFFER, tileLines(i), gl.STATIC_DRAW);
    }
    redraw();
  }

  function update() { drawColorBar(); redraw(); }

  buildPanel();
  document.addEventListener("change", (e) => {
    const t = e.target;
    if (t.name === "color") state.color = t.value;
    else if (t.name === "layout") state.layout = t.value;
    else if (t.id === "show-original") state.show.original = t.checked;
    else if (t.id === "show-decoded") state.show.decoded = t.checked;
    else if (t.id === "show-tiles") state.tiles = t.checked;
    else if (t.id === "show-embedding") state.embedding = t.checked;
    else if (t.id === "moving-budget") state.movingBudget = Number(t.value);
    else if (t.id === "error-max") state.errorMax = Math.max(Number(t.value) || 0, 1e-6);
    update();
  });
  $("point-size").addEventListener("input", (e) => { state.pointSize = Number(e.target.value); redraw(); });
  $("detail").addEventListener("input", (e) => { state.detail = Number(e.target.value); redraw(); });
  $("view-reset").addEventListener("click", () => { resetCamera(false); redraw(); });
  $("view-top").addEventListener("click", () => { resetCamera(true); redraw(); });

  // ---- mouse and touch
  const pointers = new Map();
  let pinch = null;
  function pan(dx, dy) {
    const { right, up } = cameraBasis();
    const perPixel = 2 * camera.distance * Math.tan(FOV / 2) / Math.max(canvas.clientHeight, 1);
    camera.target = camera.target.map((v, k) => v - (dx * right[k] - dy * up[k]) * perPixel);
  }
  function orbit(dx, dy) {
    camera.yaw -= dx * 0.008;
    camera.pitch = Math.min(Math.max(camera.pitch + dy * 0.008, -1.55), 1.5699);
  }
  function zoom(factor) { camera.zoom = Math.min(Math.max(camera.zoom * factor, 1e-3), 50); }
  function pinchState() {
    const [a, b] = [...pointers.values()];
    return { d: Math.hypot(a.x - b.x, a.y - b.y), x: (a.x + b.x) / 2, y: (a.y + b.y) / 2 };
  }
  canvas.addEventListener("contextmenu", (e) => e.preventDefault());
  canvas.addEventListener("pointerdown", (e) => {
    canvas.setPointerCapture(e.pointerId);
    pointers.set(e.pointerId, { x: e.clientX, y: e.clientY, button: e.button, shift: e.shiftKey });
    pinch = pointers.size === 2 ? pinchState() : null;
  });
  canvas.addEventListener("pointermove", (e) => {
    const p = pointers.get(e.pointerId);
    if (!p) return;
    const dx = e.clientX - p.x, dy = e.clientY - p.y;
    p.x = e.clientX; p.y = e.clientY;
    if (pointers.size === 2 && pinch) {
      const now = pinchState();
      zoom(pinch.d / Math.max(now.d, 1));
      pan(now.x - pinch.x, now.y - pinch.y);
      pinch = now;
    } else if (pointers.size === 1) {
      if (p.button === 2 || p.button === 1 || e.shiftKey) pan(dx, dy); else orbit(dx, dy);
    }
    markMoving();
  });
  const release = (e) => { pointers.delete(e.pointerId); pinch = pointers.size === 2 ? pinchState() : null; };
  canvas.addEventListener("pointerup", release);
  canvas.addEventListener("pointercancel", release);
  canvas.addEventListener("wheel", (e) => { e.preventDefault(); zoom(Math.exp(e.deltaY * 0.001)); markMoving(); },
    { passive: false });
  window.addEventListener("keydown", (e) => {
    if (e.target.tagName === "INPUT") return;
    if (e.key === "r") resetCamera(false); else if (e.key === "t") resetCamera(true); else return;
    redraw();
  });
  window.addEventListener("resize", redraw);

  drawColorBar();
  draw();
})();
