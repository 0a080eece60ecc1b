"use strict";
// flashmat's neural material viewer (docs/VIEWER.md). Everything it needs is
// in this page: the network and the map as base64 blocks, the GLSL in the
// x-shader scripts. URL fragment (all optional):
//   #light=X,Y,Z&view=X,Y,Z&exposure=STOPS&show=photo
//   &test=1   render once at full resolution and write the canvas pixels
//             (base64 RGB, rows from the top) into <pre id="pixels">
//   &bench=N  render N full-resolution frames, write the rate into <pre id="bench">
(function () {
  const $ = (id) => document.getElementById(id);
  const status = (msg) => { $("status").textContent = msg; };

  function decodeBase64(id) {
    const s = atob($(id).textContent.trim());
    const bytes = new Uint8Array(s.length);
    for (let i = 0; i < s.length; i++) bytes[i] = s.charCodeAt(i);
    return bytes;
  }

  function parseFragment() {
    const out = {};
    for (const part of location.hash.replace(/^#/, "").split("&")) {
      if (!part) continue;
      const [k, v = ""] = part.split("=");
      out[decodeURIComponent(k)] = decodeURIComponent(v);
    }
    return out;
  }

  function parseVec3(s, what) {
    const v = s.split(",").map(Number);
    if (v.length !== 3 || !v.every(Number.isFinite)) throw new Error(`${what} must be X,Y,Z, got '${s}'`);
    if (!(v[2] > 0)) throw new Error(`${what} must be above the material: z > 0, got '${s}'`);
    return v;
  }

  // Positions are kept at 6 decimals, so the printed command reproduces the view exactly.
  const round6 = (v) => Math.round(v * 1e6) / 1e6;
  const fmt = (p) => p.map((x) => String(round6(x))).join(",");

  function main() {
    const meta = JSON.parse($("flashmat-meta").textContent);
    if (meta.format !== "flashmat-viewer" || meta.version !== 1) throw new Error("unknown data block " + meta.format + " " + meta.version);
    const frag = parseFragment();
    const testMode = frag.test === "1";
    const benchFrames = frag.bench ? Math.max(1, parseInt(frag.bench, 10) || 1) : 0;

    const canvas = $("view");
    const gl = canvas.getContext("webgl2", { preserveDrawingBuffer: true, antialias: false, depth: false, alpha: false });
    if (!gl) throw new Error("this browser has no WebGL2: the viewer needs it");
    if (!gl.getExtension("EXT_color_buffer_float")) throw new Error("WebGL2 lacks EXT_color_buffer_float (float render targets): cannot run the network");
    const maxTex = gl.getParameter(gl.MAX_TEXTURE_SIZE);
    const maxLayers = gl.getParameter(gl.MAX_ARRAY_TEXTURE_LAYERS);
    const maxDraw = Math.min(8, gl.getParameter(gl.MAX_DRAW_BUFFERS));
    const maxView = gl.getParameter(gl.MAX_VIEWPORT_DIMS);

    // ---- data -------------------------------------------------------------------------
    const C = meta.channels, mapG = Math.ceil(C / 4);
    const W0 = meta.width, H0 = meta.height;
    // Rectangular maps: the shorter side spans [-1, 1], the longer [-a, a] (square pixels).
    const extent = [W0 / Math.min(W0, H0), H0 / Math.min(W0, H0)];
    const wBytes = decodeBase64("flashmat-weights");
    // f16 bits or f32 values (meta.weightBits)
    const weights = meta.weightBits === 32 ? new Float32Array(wBytes.buffer, 0, wBytes.length / 4) : new Uint16Array(wBytes.buffer, 0, wBytes.length / 2);
    const mapBytes = decodeBase64("flashmat-map");
    const u8 = meta.map.bits === 8, f32 = meta.map.bits === 32;
    let mapData = u8 ? mapBytes : f32 ? new Float32Array(mapBytes.buffer, 0, mapBytes.length / 4) : new Uint16Array(mapBytes.buffer, 0, mapBytes.length / 2);
    const photoBytes = decodeBase64("flashmat-photo");
    let photoData = new Uint16Array(photoBytes.buffer, 0, photoBytes.length / 2);

    // Maps beyond the GPU's texture size are shown subsampled (the centre pixel of each f x f block).
    const f = Math.max(1, Math.ceil(Math.max(W0, H0) / Math.min(maxTex, maxView[0], maxView[1])));
    const W = Math.ceil(W0 / f), H = Math.ceil(H0 / f);
    if (f > 1) {
      const pick = (src, layers, comps) => {
        const dst = new src.constructor(layers * W * H * comps);
        for (let l = 0; l < layers; l++)
          for (let i = 0; i < H; i++)
            for (let j = 0; j < W; j++) {
              const si = Math.min(H0 - 1, i * f + (f >> 1)), sj = Math.min(W0 - 1, j * f + (f >> 1));
              for (let c = 0; c < comps; c++) dst[((l * H + i) * W + j) * comps + c] = src[((l * H0 + si) * W0 + sj) * comps + c];
            }
        return dst;
      };
      mapData = pick(mapData, mapG, 4);
      photoData = pick(photoData, 1, 3);
    }
    if (mapG > maxLayers) throw new Error(`${mapG} map layers exceed this GPU's ${maxLayers}`);
    canvas.width = W;
    canvas.height = H;

    const layers = meta.layers;
    const macsPerPixel = layers.reduce((s, l) => s + l.out * l.in, 0);
    const actLayers = Math.max(...layers.map((l) => l.outPad / 4));
    // Tile side: the two activation arrays (RGBA32F) stay within 128 MiB.
    let T = 512;
    while (T > 16 && 2 * T * T * actLayers * 16 > 128 * 1024 * 1024) T >>= 1;
    T = Math.min(T, 1 << Math.ceil(Math.log2(Math.max(W, H))));

    // ---- GL resources -----------------------------------------------------------------
    function texture2D(internal, w, h, format, type, data) {
      const t = gl.createTexture();
      gl.bindTexture(gl.TEXTURE_2D, t);
      gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
      gl.texImage2D(gl.TEXTURE_2D, 0, internal, w, h, 0, format, type, data);
      for (const p of [gl.TEXTURE_MIN_FILTER, gl.TEXTURE_MAG_FILTER]) gl.texParameteri(gl.TEXTURE_2D, p, gl.NEAREST);
      return t;
    }
    function textureArray(internal, w, h, n, format, type, data) {
      const t = gl.createTexture();
      gl.bindTexture(gl.TEXTURE_2D_ARRAY, t);
      gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
      gl.texImage3D(gl.TEXTURE_2D_ARRAY, 0, internal, w, h, n, 0, format, type, data);
      for (const p of [gl.TEXTURE_MIN_FILTER, gl.TEXTURE_MAG_FILTER]) gl.texParameteri(gl.TEXTURE_2D_ARRAY, p, gl.NEAREST);
      return t;
    }
    // Weights: one uniform buffer per pass of up to `maxDraw` groups of 4 output
    // channels, as many as the GPU's uniform block size holds.
    const NW = Math.min(4096, Math.floor(gl.getParameter(gl.MAX_UNIFORM_BLOCK_SIZE) / 16));
    const halfToFloat = (h) => {
      const e = (h >> 10) & 31, m = h & 1023, sign = h & 0x8000 ? -1 : 1;
      if (e === 0) return sign * m * Math.pow(2, -24);
      if (e === 31) return m ? NaN : sign * Infinity;
      return sign * (1024 + m) * Math.pow(2, e - 25);
    };
    const plans = layers.map((L) => {
      const inG = L.inPad / 4, groups = L.outPad / 4;
      const per = Math.min(maxDraw, Math.floor(NW / (4 * inG)));
      if (per < 1) throw new Error(`layer ${L.name} (${L.inPad} inputs) does not fit this GPU's uniform block size (${NW * 16} bytes)`);
      const passes = [];
      for (let g0 = 0; g0 < groups; g0 += per) {
        const n = Math.min(per, groups - g0);
        const data = new Float32Array(NW * 4);
        for (let r = 0; r < 4 * n; r++) {
          const src = L.offset + (4 * g0 + r) * L.inPad; // layer rows of inPad values
          for (let c = 0; c < 4 * inG; c++) data[r * inG * 4 + c] = meta.weightBits === 32 ? weights[src + c] : halfToFloat(weights[src + c]);
        }
        const ubo = gl.createBuffer();
        gl.bindBuffer(gl.UNIFORM_BUFFER, ubo);
        gl.bufferData(gl.UNIFORM_BUFFER, data, gl.STATIC_DRAW);
        passes.push({ g0, n, ubo });
      }
      return { inG, passes };
    });
    const mapTex = u8 ? textureArray(gl.RGBA8, W, H, mapG, gl.RGBA, gl.UNSIGNED_BYTE, mapData)
      : f32 ? textureArray(gl.RGBA32F, W, H, mapG, gl.RGBA, gl.FLOAT, mapData)
      : textureArray(gl.RGBA16F, W, H, mapG, gl.RGBA, gl.HALF_FLOAT, mapData);
    const photoTex = texture2D(gl.RGB16F, W, H, gl.RGB, gl.HALF_FLOAT, photoData);
    const acts = [0, 1].map(() => textureArray(gl.RGBA32F, T, T, actLayers, gl.RGBA, gl.FLOAT, null));
    const outFull = texture2D(gl.RGBA32F, W, H, gl.RGBA, gl.FLOAT, null);
    const outLow = texture2D(gl.RGBA32F, W, H, gl.RGBA, gl.FLOAT, null);
    const mapOffset = new Float32Array(mapG * 4), mapScale = new Float32Array(mapG * 4).fill(1);
    if (u8) for (let c = 0; c < C; c++) { mapOffset[c] = meta.map.offset[c]; mapScale[c] = meta.map.scale[c]; }

    const vertexSource = "#version 300 es\nvoid main() { vec2 p = vec2(float((gl_VertexID << 1) & 2), float(gl_VertexID & 2)); gl_Position = vec4(p * 2.0 - 1.0, 0.0, 1.0); }";
    function compile(type, source) {
      const s = gl.createShader(type);
      gl.shaderSource(s, source);
      gl.compileShader(s);
      if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error("shader compile error: " + gl.getShaderInfoLog(s));
      return s;
    }
    function program(fragmentSource) {
      const p = gl.createProgram();
      gl.attachShader(p, compile(gl.VERTEX_SHADER, vertexSource));
      gl.attachShader(p, compile(gl.FRAGMENT_SHADER, fragmentSource));
      gl.linkProgram(p);
      if (!gl.getProgramParameter(p, gl.LINK_STATUS)) throw new Error("shader link error: " + gl.getProgramInfoLog(p));
      const loc = {};
      const n = gl.getProgramParameter(p, gl.ACTIVE_UNIFORMS);
      for (let i = 0; i < n; i++) {
        const name = gl.getActiveUniform(p, i).name.replace(/\[0\]$/, "");
        loc[name] = gl.getUniformLocation(p, name);
      }
      return { p, loc };
    }
    const layerSource = $("layer-shader").textContent.trim();
    const programs = new Map();
    function layerProgram(mode, nout) {
      const key = mode + ":" + nout;
      if (!programs.has(key)) {
        let outs = "", declare = "", accumulate = "", write = "";
        for (let i = 0; i < nout; i++) {
          outs += ` layout(location = ${i}) out vec4 o${i};`;
          declare += ` vec4 a${i} = vec4(0.0);`;
          accumulate += ` ACC(${i}, a${i})`;
          write += ` o${i} = max(a${i}, uSlope * a${i});`;
        }
        const defines = [`NOUT ${nout}`, `MODE ${mode}`, `FB ${Math.ceil(meta.frequencies / 4)}`, `MAPG ${mapG}`, `NW ${NW}`,
          `OUTPUTS${outs}`, `DECLARE${declare}`, `ACCUMULATE${accumulate}`, `WRITE${write}`].map((d) => `#define ${d}\n`).join("");
        const src = layerSource.replace(/^(#version[^\n]*\n)/, "$1" + defines);
        const prog = program(src);
        gl.uniformBlockBinding(prog.p, gl.getUniformBlockIndex(prog.p, "Weights"), 0);
        programs.set(key, prog);
      }
      return programs.get(key);
    }
    const display = program($("display-shader").textContent.trim());
    gl.bindVertexArray(gl.createVertexArray());

    const fbos = new Map();
    function arrayTarget(tex, first, n) {
      const key = tex === acts[0] ? 0 : 1;
      const k = `${key}:${first}:${n}`;
      if (!fbos.has(k)) {
        const fb = gl.createFramebuffer();
        gl.bindFramebuffer(gl.FRAMEBUFFER, fb);
        for (let i = 0; i < n; i++) gl.framebufferTextureLayer(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0 + i, tex, 0, first + i);
        fbos.set(k, fb);
      }
      return fbos.get(k);
    }
    function textureTarget(tex) {
      if (!fbos.has(tex)) {
        const fb = gl.createFramebuffer();
        gl.bindFramebuffer(gl.FRAMEBUFFER, fb);
        gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, tex, 0);
        fbos.set(tex, fb);
      }
      return fbos.get(tex);
    }
    const drawBuffers = (n) => Array.from({ length: n }, (_, i) => gl.COLOR_ATTACHMENT0 + i);

    // ---- the network ------------------------------------------------------------------
    const state = { light: meta.light.slice(), view: meta.view.slice(), exposure: 0, showPhoto: false, mode: "light" };

    // Runs every layer for the render pixels [x0, x0 + w) x [y0, y0 + h) (rows from the
    // top) of a RW x RH render, writing ln(1 + R) into `out` at the same pixels.
    function renderTile(out, RW, RH, x0, y0, w, h) {
      let src = 0;
      for (let li = 0; li < layers.length; li++) {
        const L = layers[li];
        const last = li === layers.length - 1;
        const mode = li === 0 ? 0 : L.name === "m_render.0" ? 2 : 1;
        const dst = 1 - src;
        for (const { g0, n, ubo } of plans[li].passes) {
          const { p, loc } = layerProgram(mode, n);
          gl.bindBufferBase(gl.UNIFORM_BUFFER, 0, ubo);
          gl.useProgram(p);
          if (last) {
            gl.bindFramebuffer(gl.FRAMEBUFFER, textureTarget(out));
            gl.drawBuffers([gl.COLOR_ATTACHMENT0]);
            gl.viewport(x0, y0, w, h);
            gl.uniform2i(loc.uTarget0, x0, y0);
          } else {
            gl.bindFramebuffer(gl.FRAMEBUFFER, arrayTarget(acts[dst], g0, n));
            gl.drawBuffers(drawBuffers(n));
            gl.viewport(0, 0, w, h);
            gl.uniform2i(loc.uTarget0, 0, 0);
          }
          gl.activeTexture(gl.TEXTURE1); gl.bindTexture(gl.TEXTURE_2D_ARRAY, acts[src]);
          gl.activeTexture(gl.TEXTURE2); gl.bindTexture(gl.TEXTURE_2D_ARRAY, mapTex);
          if (loc.uIn) gl.uniform1i(loc.uIn, 1);
          if (loc.uMap) {
            gl.uniform1i(loc.uMap, 2);
            gl.uniform4fv(loc.uMapOffset, mapOffset);
            gl.uniform4fv(loc.uMapScale, mapScale);
          }
          gl.uniform1i(loc.uInGroups, plans[li].inG);
          gl.uniform1f(loc.uSlope, L.slope);
          gl.uniform2i(loc.uTile, x0, y0);
          gl.uniform2i(loc.uRender, RW, RH);
          gl.uniform2i(loc.uMapSize, W, H);
          if (loc.uStep) gl.uniform2f(loc.uStep, 2 / W, -2 / H);
          if (loc.uExtent) gl.uniform2f(loc.uExtent, extent[0], extent[1]);
          if (loc.uLight) gl.uniform3fv(loc.uLight, state.light);
          if (loc.uView) gl.uniform3fv(loc.uView, state.view);
          gl.drawArrays(gl.TRIANGLES, 0, 3);
        }
        src = dst;
      }
    }

    function tilesOf(RW, RH, side) {
      const t = [];
      for (let y = 0; y < RH; y += side) for (let x = 0; x < RW; x += side) t.push([x, y, Math.min(side, RW - x), Math.min(side, RH - y)]);
      return t;
    }

    function show(out, RW, RH) {
      gl.bindFramebuffer(gl.FRAMEBUFFER, null);
      gl.drawBuffers([gl.BACK]);
      gl.viewport(0, 0, W, H);
      gl.useProgram(display.p);
      gl.activeTexture(gl.TEXTURE0); gl.bindTexture(gl.TEXTURE_2D, out);
      gl.activeTexture(gl.TEXTURE1); gl.bindTexture(gl.TEXTURE_2D, photoTex);
      gl.uniform1i(display.loc.uOut, 0);
      gl.uniform1i(display.loc.uPhoto, 1);
      gl.uniform1i(display.loc.uShowPhoto, state.showPhoto ? 1 : 0);
      gl.uniform1f(display.loc.uExposure, Math.pow(2, state.exposure));
      gl.uniform3f(display.loc.uGain, meta.gain[0], meta.gain[1], meta.gain[2]);
      gl.uniform2i(display.loc.uRender, RW, RH);
      gl.uniform2i(display.loc.uCanvas, W, H);
      gl.drawArrays(gl.TRIANGLES, 0, 3);
    }

    function renderFull() {
      for (const [x, y, w, h] of tilesOf(W, H, T)) renderTile(outFull, W, H, x, y, w, h);
      show(outFull, W, H);
    }

    // ---- URL fragment -----------------------------------------------------------------
    if (frag.light) state.light = parseVec3(frag.light, "light");
    if (frag.view) state.view = parseVec3(frag.view, "view");
    if (frag.exposure) state.exposure = Number(frag.exposure) || 0;
    state.showPhoto = frag.show === "photo";

    // ---- headless modes ---------------------------------------------------------------
    if (testMode) {
      renderFull();
      const px = new Uint8Array(W * H * 4);
      gl.readPixels(0, 0, W, H, gl.RGBA, gl.UNSIGNED_BYTE, px);
      let bin = "";
      for (let i = 0; i < H; i++) {
        const row = H - 1 - i; // readPixels starts at the bottom row
        let s = "";
        for (let j = 0; j < W; j++) {
          const k = (row * W + j) * 4;
          s += String.fromCharCode(px[k], px[k + 1], px[k + 2]);
        }
        bin += s;
      }
      const pre = $("pixels");
      pre.dataset.width = W;
      pre.dataset.height = H;
      pre.textContent = btoa(bin);
    }
    if (benchFrames) {
      const one = new Uint8Array(4);
      renderFull();
      gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, one); // warm-up: compiles the shaders
      const t0 = performance.now();
      for (let i = 0; i < benchFrames; i++) {
        state.light[0] = round6(Math.cos(i) * 0.5); // a moving light: nothing cached
        renderFull();
        gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, one);
      }
      const ms = (performance.now() - t0) / benchFrames;
      $("bench").textContent = `frames=${benchFrames} size=${W}x${H} ms_per_frame=${ms.toFixed(1)} fps=${(1000 / ms).toFixed(3)} macs_per_frame=${macsPerPixel * W * H} renderer=${gl.getParameter(gl.RENDERER)}`;
    }
    if (testMode || benchFrames) {
      status("");
      document.body.dataset.ready = "1";
      return;
    }

    // ---- interactive loop -------------------------------------------------------------
    // Every change renders at once at a resolution 1/scale that the measured speed
    // allows (~30 ms), then, when nothing moved for a moment, the full resolution in
    // tiles spread over frames, shown once complete.
    let msPerPixel = 0;          // measured GPU cost (upper bound until a slow frame measures it)
    let dirty = true, lastChange = 0;
    let fullValid = false, sharpen = null;
    let pending = null;          // {sync, t0, pixels}
    let frames = 0, fpsT0 = performance.now();
    const frameBudget = 30, idleMs = 150;

    function changed() {
      dirty = true;
      lastChange = performance.now();
      fullValid = false;
      sharpen = null;
      updateText();
    }

    function scaleFor() {
      if (!msPerPixel) return 1;
      let s = 1;
      while (s < 16 && msPerPixel * (W / s) * (H / s) > frameBudget) s *= 2;
      return s;
    }

    function measure(pixels) {
      if (pending) return; // one fence in flight
      pending = { sync: gl.fenceSync(gl.SYNC_GPU_COMMANDS_COMPLETE, 0), t0: performance.now(), pixels };
      gl.flush();
    }
    function poll(now) {
      if (!pending) return;
      if (gl.getSyncParameter(pending.sync, gl.SYNC_STATUS) !== gl.SIGNALED) return;
      const ms = now - pending.t0, per = ms / pending.pixels;
      // Done within about a frame: the cost is at most that (the wait was the display's).
      msPerPixel = ms > 40 || !msPerPixel ? per : Math.min(msPerPixel, per);
      gl.deleteSync(pending.sync);
      pending = null;
    }

    let lastScale = 1;
    function frame(now) {
      poll(now);
      if (state.showPhoto) {
        if (dirty) { show(fullValid ? outFull : outLow, W, H); dirty = false; }
      } else if (dirty) {
        const s = scaleFor();
        lastScale = s;
        const RW = Math.ceil(W / s), RH = Math.ceil(H / s);
        const out = s === 1 ? outFull : outLow;
        for (const [x, y, w, h] of tilesOf(RW, RH, T)) renderTile(out, RW, RH, x, y, w, h);
        show(out, RW, RH);
        measure(RW * RH);
        fullValid = s === 1;
        dirty = false;
        frames++;
      } else if (!fullValid && now - lastChange > idleMs) {
        if (!sharpen) {
          let side = T;
          while (side > 32 && msPerPixel * side * side > frameBudget) side >>= 1;
          sharpen = { tiles: tilesOf(W, H, side), next: 0 };
        }
        // As many tiles as fit the frame budget at the measured cost (at least one).
        let budget = frameBudget;
        do {
          const [x, y, w, h] = sharpen.tiles[sharpen.next++];
          renderTile(outFull, W, H, x, y, w, h);
          budget -= msPerPixel * w * h;
        } while (sharpen.next < sharpen.tiles.length && budget > 0 && msPerPixel > 0);
        if (sharpen.next >= sharpen.tiles.length) {
          show(outFull, W, H);
          measure(W * H);
          fullValid = true;
          sharpen = null;
          lastScale = 1;
          frames++;
        }
      }
      const dt = now - fpsT0;
      if (dt > 1000) {
        $("fps").textContent = `${(frames * 1000 / dt).toFixed(1)} fps`;
        frames = 0;
        fpsT0 = now;
      }
      $("resolution").textContent = state.showPhoto ? "input photo" : lastScale === 1 && fullValid
        ? `${W}x${H}, full resolution` : `${Math.ceil(W / lastScale)}x${Math.ceil(H / lastScale)} while moving`;
      requestAnimationFrame(frame);
    }

    // ---- controls ---------------------------------------------------------------------
    const d = meta.identity[2];
    const heightEl = $("height"), exposureEl = $("exposure");
    function updateText() {
      state.light = state.light.map(round6);
      state.view = state.view.map(round6);
      $("light-pos").textContent = `(${fmt(state.light)})`;
      $("view-pos").textContent = `(${fmt(state.view)})`;
      heightEl.value = state.light[2];
      $("height-value").textContent = state.light[2].toFixed(2);
      exposureEl.value = state.exposure;
      $("exposure-value").textContent = `${state.exposure >= 0 ? "+" : ""}${Number(state.exposure).toFixed(1)} stops`;
      $("photo").classList.toggle("on", state.showPhoto);
      $("photo").textContent = state.showPhoto ? "Show neural render (P)" : "Show input photo (P)";
      $("command").textContent = `flashmat relight ${/[\s"'$]/.test(meta.relightInput) ? JSON.stringify(meta.relightInput) : meta.relightInput} --light=${fmt(state.light)} --view=${fmt(state.view)} -o view.png`;
      const h = `#light=${fmt(state.light)}&view=${fmt(state.view)}` + (state.exposure ? `&exposure=${state.exposure}` : "") + (state.showPhoto ? "&show=photo" : "");
      if (location.hash !== h) history.replaceState(null, "", h);
    }
    function setMode(m) {
      state.mode = m;
      $("mode-light").classList.toggle("on", m === "light");
      $("mode-camera").classList.toggle("on", m === "camera");
      canvas.classList.toggle("camera", m === "camera");
    }
    function materialPoint(e) {
      const r = canvas.getBoundingClientRect();
      return [(2 * (e.clientX - r.left) / r.width - 1) * extent[0], (1 - 2 * (e.clientY - r.top) / r.height) * extent[1]];
    }
    let drag = null;
    canvas.addEventListener("pointerdown", (e) => {
      canvas.setPointerCapture(e.pointerId);
      drag = { x: e.clientX, y: e.clientY, view: state.view.slice() };
      if (state.mode === "light") pointerLight(e);
    });
    canvas.addEventListener("pointerup", () => { drag = null; });
    function pointerLight(e) {
      const [x, y] = materialPoint(e);
      state.light = [x, y, state.light[2]];
      changed();
    }
    canvas.addEventListener("pointermove", (e) => {
      if (state.mode === "light") { pointerLight(e); return; }
      if (!drag) return;
      // Camera: azimuth and polar angle from the drag, distance kept.
      const v = drag.view, r = Math.hypot(...v);
      let az = Math.atan2(v[1], v[0]) - (e.clientX - drag.x) * 0.01;
      let pol = Math.acos(v[2] / r) + (e.clientY - drag.y) * 0.01;
      pol = Math.min(Math.max(pol, 0), 85 * Math.PI / 180);
      state.view = [r * Math.sin(pol) * Math.cos(az), r * Math.sin(pol) * Math.sin(az), r * Math.cos(pol)];
      changed();
    });
    canvas.addEventListener("wheel", (e) => {
      e.preventDefault();
      const k = Math.exp(-e.deltaY * 0.001);
      if (state.mode === "light") state.light[2] = Math.min(Math.max(state.light[2] * k, 0.05), 50);
      else {
        const r = Math.hypot(...state.view), nr = Math.min(Math.max(r / k, 1.1), 50);
        state.view = state.view.map((c) => c * nr / r);
      }
      changed();
    }, { passive: false });
    heightEl.addEventListener("input", () => { state.light[2] = Math.max(0.05, Number(heightEl.value)); changed(); });
    exposureEl.addEventListener("input", () => { state.exposure = Number(exposureEl.value); dirty = true; updateText(); show(fullValid ? outFull : outLow, W, H); });
    $("mode-light").onclick = () => setMode("light");
    $("mode-camera").onclick = () => setMode("camera");
    const togglePhoto = () => { state.showPhoto = !state.showPhoto; changed(); };
    const identity = () => { state.light = meta.identity.slice(); state.view = meta.identity.slice(); changed(); };
    function save() {
      canvas.toBlob((blob) => {
        const a = document.createElement("a");
        a.href = URL.createObjectURL(blob);
        a.download = `${meta.source.replace(/\.[^.]*$/, "")}-light_${fmt(state.light)}-view_${fmt(state.view)}.png`;
        a.click();
        setTimeout(() => URL.revokeObjectURL(a.href), 1000);
      }, "image/png");
    }
    $("photo").onclick = togglePhoto;
    $("identity").onclick = identity;
    $("save").onclick = save;
    window.addEventListener("keydown", (e) => {
      if (e.target.tagName === "INPUT") return;
      const k = e.key.toLowerCase();
      if (k === "p") togglePhoto();
      else if (k === "i") identity();
      else if (k === "s") save();
      else if (k === "l") setMode("light");
      else if (k === "c") setMode("camera");
    });

    // Ratios as `flashmat estimate` prints them; a channel the photo holds at 0 is "-" (JSON null).
    const ratio = (v) => (typeof v === "number" && isFinite(v) ? v.toFixed(2) : "-");
    $("name").textContent = meta.source;
    $("info").textContent = `${meta.preset} preset (${meta.modelId}), ${C}-channel ${W0}x${H0} neural map` +
      (f > 1 ? ` shown at ${W}x${H} (GPU texture limit ${maxTex})` : "") +
      `, ${meta.map.bits}-bit map, ${meta.weightBits}-bit weights; ${(macsPerPixel / 1000).toFixed(1)}k multiply-adds per pixel, ` +
      `${(macsPerPixel * W * H / 1e9).toFixed(2)} G per full frame; d = ${d.toFixed(4)}` +
      (meta.identityCheck ? `; identity render over the photo: brightness ${ratio(meta.identityCheck.brightness)}, ` +
        `R / G / B ${meta.identityCheck.rgb.map(ratio).join(" / ")}` : "");
    updateText();
    status("");
    requestAnimationFrame(frame);
  }

  try {
    main();
  } catch (e) {
    status("error: " + (e && e.message ? e.message : e));
    document.body.dataset.ready = "error";
  }
})();
