// Persona's 3D view: the puppet of a report, drawn with WebGL from the .glb file Persona wrote.
//
// It reads the two kinds of glTF 2.0 binary files persona.stores.gltf writes, and nothing more general:
// a textured mesh (a person's average face), and a mesh with one morph target per frame, its node's
// scale turning 16-bit positions into metres (KHR_mesh_quantization), the node above it rotated and
// moved per frame (the head's pose), the frames' times in the animation. The page embeds the file
// (a <script type="application/octet-stream" data-persona-glb> holding it in base64), so the view
// needs no network and no server: report.html opens from disk.
//
// Use: <div class="persona-3d" data-glb="ID"></div>, ID the embedded file's element; the view fills the
// div with a canvas and its controls. Drag to turn the head; "play" runs the drive at the video's rate;
// "turn" swings the view slowly from side to side. The canvas says which frame it shows
// (canvas.dataset.frame) and how many times it was drawn (canvas.dataset.draws), for tests.
(function () {
  "use strict";

  var TYPES = {5120: Int8Array, 5121: Uint8Array, 5122: Int16Array, 5123: Uint16Array, 5125: Uint32Array,
               5126: Float32Array};
  var WIDTH = {SCALAR: 1, VEC2: 2, VEC3: 3, VEC4: 4};

  // The JSON document and the binary chunk of a .glb (glTF 2.0 §4.4).
  function parseGlb(bytes) {
    var view = new DataView(bytes.buffer, bytes.byteOffset, bytes.byteLength);
    if (view.getUint32(0, true) !== 0x46546C67 || view.getUint32(4, true) !== 2) {
      throw new Error("not a glTF 2.0 binary file");
    }
    var jsonLength = view.getUint32(12, true);
    var doc = JSON.parse(new TextDecoder().decode(bytes.subarray(20, 20 + jsonLength)));
    var binLength = view.getUint32(20 + jsonLength, true);
    return {doc: doc, bin: bytes.subarray(28 + jsonLength, 28 + jsonLength + binLength)};
  }

  // An accessor's values as a Float32Array (or its own integer type for indices), count * width long,
  // byteStride and sparse values applied.
  function accessor(glb, index, keepType) {
    var a = glb.doc.accessors[index], Type = TYPES[a.componentType], width = WIDTH[a.type];
    var out = new (keepType ? Type : Float32Array)(a.count * width);
    if (a.bufferView !== undefined) {
      var v = glb.doc.bufferViews[a.bufferView];
      var stride = (v.byteStride || Type.BYTES_PER_ELEMENT * width) / Type.BYTES_PER_ELEMENT;
      var start = glb.bin.byteOffset + (v.byteOffset || 0) + (a.byteOffset || 0);
      var src = new Type(glb.bin.buffer.slice(start, start + ((a.count - 1) * stride + width) * Type.BYTES_PER_ELEMENT));
      for (var i = 0; i < a.count; i++) {
        for (var k = 0; k < width; k++) out[i * width + k] = src[i * stride + k];
      }
    }
    if (a.sparse) {
      var s = a.sparse, iv = glb.doc.bufferViews[s.indices.bufferView], vv = glb.doc.bufferViews[s.values.bufferView];
      var IndexType = TYPES[s.indices.componentType];
      var where = new IndexType(glb.bin.buffer.slice(glb.bin.byteOffset + (iv.byteOffset || 0),
        glb.bin.byteOffset + (iv.byteOffset || 0) + s.count * IndexType.BYTES_PER_ELEMENT));
      var values = new Type(glb.bin.buffer.slice(glb.bin.byteOffset + (vv.byteOffset || 0),
        glb.bin.byteOffset + (vv.byteOffset || 0) + s.count * width * Type.BYTES_PER_ELEMENT));
      for (var j = 0; j < s.count; j++) {
        for (var m = 0; m < width; m++) out[where[j] * width + m] = values[j * width + m];
      }
    }
    return out;
  }

  // 4x4 matrices, column-major as WebGL takes them.
  function multiply(a, b) {
    var out = new Float32Array(16);
    for (var c = 0; c < 4; c++) {
      for (var r = 0; r < 4; r++) {
        var sum = 0;
        for (var k = 0; k < 4; k++) sum += a[k * 4 + r] * b[c * 4 + k];
        out[c * 4 + r] = sum;
      }
    }
    return out;
  }
  function perspective(fovy, aspect, near, far) {
    var f = 1 / Math.tan(fovy / 2), out = new Float32Array(16);
    out[0] = f / aspect; out[5] = f; out[10] = (far + near) / (near - far); out[11] = -1;
    out[14] = 2 * far * near / (near - far);
    return out;
  }
  // rotation from a unit quaternion (x, y, z, w), then translation t, then uniform scale s inside
  function transform(q, t, s) {
    var x = q[0], y = q[1], z = q[2], w = q[3];
    return new Float32Array([
      s * (1 - 2 * (y * y + z * z)), s * 2 * (x * y + z * w), s * 2 * (x * z - y * w), 0,
      s * 2 * (x * y - z * w), s * (1 - 2 * (x * x + z * z)), s * 2 * (y * z + x * w), 0,
      s * 2 * (x * z + y * w), s * 2 * (y * z - x * w), s * (1 - 2 * (x * x + y * y)), 0,
      t[0], t[1], t[2], 1]);
  }
  function turn(yaw, pitch) {  // about y, then x
    var qy = [0, Math.sin(yaw / 2), 0, Math.cos(yaw / 2)], qx = [Math.sin(pitch / 2), 0, 0, Math.cos(pitch / 2)];
    return multiply(transform(qx, [0, 0, 0], 1), transform(qy, [0, 0, 0], 1));
  }
  function nlerp(a, b, f) {  // quaternions already on the same side (Persona writes them so)
    var q = [0, 0, 0, 0], n = 0;
    for (var i = 0; i < 4; i++) { q[i] = a[i] + (b[i] - a[i]) * f; n += q[i] * q[i]; }
    n = Math.sqrt(n) || 1;
    return q.map(function (v) { return v / n; });
  }

  var VERTEX = "attribute vec3 position; attribute vec3 normal; attribute vec2 uv;" +
    "uniform mat4 projection, model; varying vec2 v_uv; varying vec3 v_normal;" +
    "void main() { v_uv = uv; v_normal = mat3(model) * normal; gl_Position = projection * model * vec4(position, 1.0); }";
  var FRAGMENT = "precision mediump float; uniform sampler2D image; uniform float lit;" +
    "varying vec2 v_uv; varying vec3 v_normal;" +
    "void main() { vec3 n = normalize(v_normal); if (!gl_FrontFacing) n = -n;" +
    "float shade = mix(1.0, 0.55 + 0.45 * max(dot(n, normalize(vec3(0.3, 0.4, 1.0))), 0.0), lit);" +
    "gl_FragColor = vec4(texture2D(image, v_uv).rgb * shade, 1.0); }";

  function compile(gl, vertex, fragment) {
    var program = gl.createProgram();
    [[gl.VERTEX_SHADER, vertex], [gl.FRAGMENT_SHADER, fragment]].forEach(function (pair) {
      var shader = gl.createShader(pair[0]);
      gl.shaderSource(shader, pair[1]);
      gl.compileShader(shader);
      if (!gl.getShaderParameter(shader, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(shader));
      gl.attachShader(program, shader);
    });
    gl.linkProgram(program);
    if (!gl.getProgramParameter(program, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(program));
    return program;
  }

  // Vertex normals of the current positions: area-weighted triangle normals summed at each vertex.
  function normals(positions, indices, out) {
    out.fill(0);
    for (var i = 0; i < indices.length; i += 3) {
      var a = indices[i] * 3, b = indices[i + 1] * 3, c = indices[i + 2] * 3;
      var ux = positions[b] - positions[a], uy = positions[b + 1] - positions[a + 1], uz = positions[b + 2] - positions[a + 2];
      var vx = positions[c] - positions[a], vy = positions[c + 1] - positions[a + 1], vz = positions[c + 2] - positions[a + 2];
      var nx = uy * vz - uz * vy, ny = uz * vx - ux * vz, nz = ux * vy - uy * vx;
      out[a] += nx; out[a + 1] += ny; out[a + 2] += nz; out[b] += nx; out[b + 1] += ny; out[b + 2] += nz;
      out[c] += nx; out[c + 1] += ny; out[c + 2] += nz;
    }
    return out;
  }

  // The puppet of one .glb: its rest shape, its frames (morph targets) and head poses, drawn on canvas.
  function Puppet(canvas, bytes) {
    var glb = parseGlb(bytes), doc = glb.doc;
    var holder = doc.nodes.filter(function (n) { return n.mesh !== undefined; })[0];
    var primitive = doc.meshes[holder.mesh].primitives[0];
    this.scale = holder.scale ? holder.scale[0] : 1;
    this.rest = accessor(glb, primitive.attributes.POSITION);
    this.targets = (primitive.targets || []).map(function (t) { return accessor(glb, t.POSITION); });
    this.indices = accessor(glb, primitive.indices, true);
    this.uvs = accessor(glb, primitive.attributes.TEXCOORD_0);
    this.positions = new Float32Array(this.rest.length);
    this.normals = new Float32Array(this.rest.length);
    this.frames = 0; this.fps = 25; this.rotations = null; this.translations = null;
    var animation = (doc.animations || [])[0];
    if (animation) {
      var self = this;
      animation.channels.forEach(function (channel) {
        var sampler = animation.samplers[channel.sampler];
        if (channel.target.path === "rotation") self.rotations = accessor(glb, sampler.output);
        if (channel.target.path === "translation") self.translations = accessor(glb, sampler.output);
        if (!self.frames) {
          var times = accessor(glb, sampler.input);
          self.frames = times.length;
          if (times.length > 1) self.fps = (times.length - 1) / (times[times.length - 1] - times[0]);
        }
      });
    }
    this.lit = (doc.materials[primitive.material].extensions || {}).KHR_materials_unlit ? 0.6 : 1.0;
    var low = [Infinity, Infinity, Infinity], high = [-Infinity, -Infinity, -Infinity];
    for (var i = 0; i < this.rest.length; i++) {
      low[i % 3] = Math.min(low[i % 3], this.rest[i] * this.scale);
      high[i % 3] = Math.max(high[i % 3], this.rest[i] * this.scale);
    }
    this.centre = [0, 1, 2].map(function (k) { return (low[k] + high[k]) / 2; });  // the view turns about it
    this.radius = Math.sqrt([0, 1, 2].reduce(function (sum, k) { return sum + Math.pow(high[k] - low[k], 2); }, 0)) / 2;
    this.canvas = canvas;
    this.setup(glb, primitive);
    this.time = 0; this.yaw = 0; this.pitch = 0; this.playing = this.frames > 1; this.turning = true;
    canvas.dataset.draws = "0";
  }

  Puppet.prototype.setup = function (glb, primitive) {
    var gl = this.canvas.getContext("webgl", {antialias: true, preserveDrawingBuffer: true});
    if (!gl) throw new Error("this browser cannot draw WebGL");
    this.gl = gl;
    if (this.indices instanceof Uint32Array && !gl.getExtension("OES_element_index_uint")) {
      throw new Error("this browser cannot draw meshes of more than 65535 vertices");
    }
    this.program = compile(gl, VERTEX, FRAGMENT);
    var self = this;
    function buffer(kind, data, usage) {
      var b = gl.createBuffer();
      gl.bindBuffer(kind, b);
      gl.bufferData(kind, data, usage);
      return b;
    }
    this.buffers = {position: buffer(gl.ARRAY_BUFFER, this.positions, gl.DYNAMIC_DRAW),
                    normal: buffer(gl.ARRAY_BUFFER, this.normals, gl.DYNAMIC_DRAW),
                    uv: buffer(gl.ARRAY_BUFFER, this.uvs, gl.STATIC_DRAW),
                    index: buffer(gl.ELEMENT_ARRAY_BUFFER, this.indices, gl.STATIC_DRAW)};
    this.texture = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, this.texture);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGB, 1, 1, 0, gl.RGB, gl.UNSIGNED_BYTE, new Uint8Array([200, 200, 200]));
    var material = glb.doc.materials[primitive.material];
    var image = glb.doc.images[glb.doc.textures[material.pbrMetallicRoughness.baseColorTexture.index].source];
    var view = glb.doc.bufferViews[image.bufferView];
    var png = new Blob([glb.bin.subarray(view.byteOffset || 0, (view.byteOffset || 0) + view.byteLength)],
                       {type: image.mimeType});
    this.ready = createImageBitmap(png).then(function (bitmap) {
      gl.bindTexture(gl.TEXTURE_2D, self.texture);  // any size: no mipmaps, clamped (WebGL 1 needs that)
      gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGB, gl.RGB, gl.UNSIGNED_BYTE, bitmap);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.LINEAR);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
      gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
    });
  };

  // The positions and head pose at time t (seconds): between two frames, each blended linearly, as the
  // file's LINEAR samplers say (Persona's weights give frame k's target alone the weight 1 at frame k's
  // time, so the view reads frame k's target rather than the weights).
  Puppet.prototype.pose = function (t) {
    var q = [0, 0, 0, 1], move = [0, 0, 0], k = 0, f = 0;
    if (this.frames > 1) {
      var at = (t * this.fps) % this.frames;
      k = Math.floor(at); f = at - k;
      if (k >= this.frames - 1) { k = this.frames - 1; f = 0; }
    }
    var next = Math.min(k + 1, this.frames - 1), rest = this.rest, out = this.positions, s = this.scale;
    var a = this.targets[k], b = this.targets[next];
    for (var i = 0; i < rest.length; i++) {
      var d = a ? a[i] + (b[i] - a[i]) * f : 0;
      out[i] = (rest[i] + d) * s;
    }
    if (this.rotations) q = nlerp(this.rotations.subarray(4 * k, 4 * k + 4), this.rotations.subarray(4 * next, 4 * next + 4), f);
    if (this.translations) {
      for (var j = 0; j < 3; j++) move[j] = this.translations[3 * k + j] + (this.translations[3 * next + j] - this.translations[3 * k + j]) * f;
    }
    this.canvas.dataset.frame = String(k);
    return transform(q, move, 1);
  };

  Puppet.prototype.draw = function () {
    var gl = this.gl, p = this.program, canvas = this.canvas;
    var head = this.pose(this.time);
    normals(this.positions, this.indices, this.normals);
    gl.viewport(0, 0, canvas.width, canvas.height);
    gl.clearColor(0.93, 0.93, 0.93, 1);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    gl.enable(gl.DEPTH_TEST);
    gl.useProgram(p);
    var distance = 1.15 * this.radius / Math.tan(0.3);  // the face fills the view's height (0.6 rad)
    var camera = new Float32Array([1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, -distance, 1]);
    var centred = transform([0, 0, 0, 1], this.centre.map(function (c) { return -c; }), 1);
    var model = multiply(camera, multiply(turn(this.yaw, this.pitch), multiply(centred, head)));
    gl.uniformMatrix4fv(gl.getUniformLocation(p, "projection"), false,
                        perspective(0.6, canvas.width / canvas.height, distance / 10, distance * 10));
    gl.uniformMatrix4fv(gl.getUniformLocation(p, "model"), false, model);
    gl.uniform1f(gl.getUniformLocation(p, "lit"), this.lit);
    var attributes = [["position", this.buffers.position, this.positions, 3],
                      ["normal", this.buffers.normal, this.normals, 3], ["uv", this.buffers.uv, null, 2]];
    attributes.forEach(function (a) {
      var where = gl.getAttribLocation(p, a[0]);
      gl.bindBuffer(gl.ARRAY_BUFFER, a[1]);
      if (a[2]) gl.bufferSubData(gl.ARRAY_BUFFER, 0, a[2]);
      gl.enableVertexAttribArray(where);
      gl.vertexAttribPointer(where, a[3], gl.FLOAT, false, 0, 0);
    });
    gl.bindTexture(gl.TEXTURE_2D, this.texture);
    gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, this.buffers.index);
    gl.drawElements(gl.TRIANGLES, this.indices.length,
                    this.indices instanceof Uint32Array ? gl.UNSIGNED_INT : gl.UNSIGNED_SHORT, 0);
    canvas.dataset.draws = String(Number(canvas.dataset.draws) + 1);
  };

  // Plays and turns the puppet in time with the page's frames; the controls below the canvas.
  Puppet.prototype.run = function (controls) {
    var self = this, last = null, start = performance.now(), drag = null;
    function tick(now) {
      if (last !== null && self.playing) self.time += (now - last) / 1000;
      last = now;
      if (self.turning && !drag) self.yaw = 0.6 * Math.sin((now - start) / 2500);
      self.draw();
      controls.label.textContent = self.frames > 1 ? "frame " + self.canvas.dataset.frame + " of " + self.frames +
        " (" + self.fps.toFixed(0) + " fps)" : "the average face";
      requestAnimationFrame(tick);
    }
    this.canvas.addEventListener("pointerdown", function (e) { drag = [e.clientX, e.clientY, self.yaw, self.pitch]; });
    window.addEventListener("pointerup", function () { drag = null; });
    window.addEventListener("pointermove", function (e) {
      if (!drag) return;
      self.turning = false; controls.turn.checked = false;
      self.yaw = drag[2] + (e.clientX - drag[0]) / 150;
      self.pitch = Math.max(-1.2, Math.min(1.2, drag[3] + (e.clientY - drag[1]) / 150));
    });
    controls.play.addEventListener("click", function () {
      self.playing = !self.playing; controls.play.textContent = self.playing ? "pause" : "play";
    });
    controls.turn.addEventListener("change", function () { self.turning = controls.turn.checked; });
    this.ready.then(function () { requestAnimationFrame(tick); });
  };

  function base64Bytes(text) {
    var raw = atob(text.replace(/\s+/g, "")), out = new Uint8Array(raw.length);
    for (var i = 0; i < raw.length; i++) out[i] = raw.charCodeAt(i);
    return out;
  }

  function show(holder) {
    var source = document.getElementById(holder.dataset.glb);
    var canvas = document.createElement("canvas");
    canvas.width = Number(holder.dataset.width || 480); canvas.height = Number(holder.dataset.height || 480);
    canvas.style.cursor = "grab"; canvas.title = "drag to turn the head";
    var bar = document.createElement("div"), play = document.createElement("button"), label = document.createElement("span");
    var turnBox = document.createElement("label"), turnInput = document.createElement("input");
    turnInput.type = "checkbox"; turnInput.checked = true;
    turnBox.appendChild(turnInput); turnBox.appendChild(document.createTextNode(" turn "));
    play.textContent = "pause";
    bar.appendChild(play); bar.appendChild(turnBox); bar.appendChild(label);
    holder.appendChild(canvas); holder.appendChild(bar);
    try {
      var puppet = new Puppet(canvas, base64Bytes(source.textContent));
      if (puppet.frames < 2) { play.disabled = true; play.textContent = "play"; }
      puppet.run({play: play, turn: turnInput, label: label});
      holder.puppet = puppet;
    } catch (err) {  // said on the page, where the view would be, and in the console
      var note = document.createElement("p");
      note.textContent = "The 3D view cannot be shown here: " + err.message;
      holder.replaceChildren(note);
      console.warn("Persona 3D view: " + err.message);
    }
  }

  window.PersonaViewer = {parseGlb: parseGlb, show: show};
  function start() { document.querySelectorAll(".persona-3d[data-glb]").forEach(show); }
  if (document.readyState === "loading") document.addEventListener("DOMContentLoaded", start); else start();
})();
