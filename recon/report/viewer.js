// lfrig's 3D view of a report's model: draws window.LFRIG_MODEL (model-data.js) with three.js
// (three.viewer.min.js, the global THREE). Orbit with the left mouse button, pan with the right,
// zoom with the wheel; the buttons recolour the model by the centre view, depth or confidence.
// Coordinates are mm in the centre camera's frame (x right, y down, z forward); the view starts on
// the centre camera's side of the model, turned a little so that depth shows.
(function () {
  "use strict";
  var box = document.getElementById("lfrig-3d");
  if (!box) return;
  var status = box.querySelector(".status");
  function say(text) { if (status) status.textContent = text; }
  if (typeof THREE === "undefined" || !THREE.WebGLRenderer) {
    say("The 3D view's library (three.viewer.min.js) is missing from this folder.");
    throw new Error("lfrig 3D view: three.viewer.min.js did not load");
  }
  var data = window.LFRIG_MODEL;
  if (!data || !data.positions) {
    say("The 3D view's data (model-data.js) is missing from this folder.");
    throw new Error("lfrig 3D view: model-data.js did not load");
  }

  function bytes(text) {
    var raw = atob(text), out = new Uint8Array(raw.length);
    for (var i = 0; i < raw.length; i++) out[i] = raw.charCodeAt(i);
    return out;
  }
  var positions = new Float32Array(bytes(data.positions).buffer);

  var canvas = box.querySelector("canvas");
  var renderer;
  try {
    renderer = new THREE.WebGLRenderer({ canvas: canvas, antialias: true, alpha: true, preserveDrawingBuffer: true });
  } catch (error) {
    say("This browser cannot draw WebGL, so the 3D view is off; the model is in the PLY file.");
    return;
  }
  renderer.setPixelRatio(Math.min(window.devicePixelRatio || 1, 2));
  renderer.setClearColor(0x000000, 0);  // the page's background shows through
  renderer.outputColorSpace = "srgb-linear";  // the colours are sRGB already: written out as they are

  var geometry = new THREE.BufferGeometry();
  geometry.setAttribute("position", new THREE.BufferAttribute(positions, 3));
  if (data.indices) geometry.setIndex(new THREE.BufferAttribute(new Uint32Array(bytes(data.indices).buffer), 1));
  var colourings = data.colourings || {};
  var names = Object.keys(colourings);
  var colourAttrs = {};
  names.forEach(function (name) {
    colourAttrs[name] = new THREE.BufferAttribute(bytes(colourings[name].rgb), 3, true);
  });
  var first = names.length ? names[0] : null;
  if (first) geometry.setAttribute("color", colourAttrs[first]);

  var object;
  if (data.kind === "mesh") {
    geometry.computeVertexNormals();
    object = new THREE.Mesh(geometry, new THREE.MeshLambertMaterial({
      vertexColors: !!first, color: first ? 0xffffff : 0xb0b4bc, side: THREE.DoubleSide }));
  } else {
    object = new THREE.Points(geometry, new THREE.PointsMaterial({
      vertexColors: !!first, color: first ? 0xffffff : 0x505560, size: 2, sizeAttenuation: false }));
  }
  // lfrig's camera frame (y down, z forward) to three.js's (y up, the camera looking along -z):
  // a half turn about x, which keeps the triangles' winding.
  object.rotation.x = Math.PI;

  var scene = new THREE.Scene();
  scene.add(object);
  scene.add(new THREE.AmbientLight(0xffffff, 2.4));
  var light = new THREE.DirectionalLight(0xffffff, 1.0);
  scene.add(light);

  geometry.computeBoundingSphere();
  var sphere = geometry.boundingSphere.clone();
  sphere.center.applyEuler(object.rotation);
  var radius = Math.max(sphere.radius, 1e-3);
  var camera = new THREE.PerspectiveCamera(40, 1, radius / 1000, radius * 100);
  // on the line from the centre camera (the origin) to the model, as far as the model needs to fit,
  // then turned a little to the left and up so that depth shows at once
  var distance = sphere.center.length();
  var fit = 0.8 * radius / Math.sin((40 / 2) * Math.PI / 180);
  var direction = distance > 1e-6 ? sphere.center.clone().normalize() : new THREE.Vector3(0, 0, -1);
  var offset = direction.clone().multiplyScalar(-fit);
  offset.applyAxisAngle(new THREE.Vector3(0, 1, 0), -0.35).applyAxisAngle(new THREE.Vector3(1, 0, 0), -0.2);
  camera.position.copy(sphere.center).add(offset);
  camera.lookAt(sphere.center);
  camera.add(light);
  light.position.set(-0.5, 0.6, 1);
  scene.add(camera);

  var controls = new THREE.OrbitControls(camera, canvas);
  controls.target.copy(sphere.center);
  controls.update();

  function resize() {
    var width = canvas.clientWidth || 640, height = canvas.clientHeight || 480;
    renderer.setSize(width, height, false);
    camera.aspect = width / height;
    camera.updateProjectionMatrix();
  }
  function render() { renderer.render(scene, camera); }
  controls.addEventListener("change", render);
  window.addEventListener("resize", function () { resize(); render(); });

  var legend = box.querySelector(".legend3d");
  function colourBy(name) {
    if (!colourAttrs[name]) return;
    geometry.setAttribute("color", colourAttrs[name]);
    if (legend) {
      var entry = colourings[name];
      legend.innerHTML = "";
      if (entry.lut) {
        var bar = document.createElement("span");
        bar.className = "ramp";
        bar.style.background = entry.lut;
        legend.appendChild(bar);
      }
      legend.appendChild(document.createTextNode(entry.legend));
    }
    box.querySelectorAll("button[data-colour]").forEach(function (button) {
      button.classList.toggle("on", button.getAttribute("data-colour") === name);
    });
    render();
  }
  box.querySelectorAll("button[data-colour]").forEach(function (button) {
    var name = button.getAttribute("data-colour");
    if (!colourAttrs[name]) { button.disabled = true; return; }
    button.addEventListener("click", function () { colourBy(name); });
  });
  var reset = box.querySelector("button[data-reset]");
  if (reset) reset.addEventListener("click", function () { controls.reset(); render(); });
  controls.saveState();

  resize();
  if (first) colourBy(first); else render();
  say("");
  box.setAttribute("data-state", "drawn");
})();
