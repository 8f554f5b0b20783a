// PRTT in three.js: a GLTFLoader plugin that shades the objects of a .glb
// exported by `prtt export` (docs/gltf.md) with PRTT's own shading GLSL
// (shaders/*.glsl through prtt_shaders.js: the very files Blender's viewport
// compiles), per pixel: TPFL (the paper's glossy PRT), TP (the full triple
// product) or diffuse, with the bounce textures: a baked bounce as it is, a
// relightable bounce relit on the GPU by the same relight pass as Blender's
// (shaders/prtt_relight_frag.glsl) whenever the light changes; a Sun lamp's
// direct light with its baked shadow masks, its colour and strength live.
//
//   const loader = new GLTFLoader();
//   loader.register((parser) => new PRTTLoaderPlugin(parser, { renderer }));
//   const gltf = await loader.loadAsync('room.glb');
//   const prtt = gltf.userData.prtt;          // null: the file has no PRTT data
//   renderer.render(gltf.scene, camera);      // three's own: PRTT's meshes relight and set their view
//   prtt.render(renderer, gltf.scene, camera); // or with a depth pre-pass (each pixel shaded once)
//   prtt.setTurn(90); prtt.setMode('diffuse', { bounces: true });
import * as THREE from 'three';
import { ZSTDDecoder } from 'three/addons/libs/zstddec.module.js';
import {
  blockName, depthVariant, fetchSources, relightSources, relightVariant, shSizes, surfaceSources, surfaceVariant,
  GAUNT_WIDTH,
  MAX_PREVIEW_BANDS, MODES,
} from './prtt_shaders.js';
import { gauntTable, lightBlock, relightBlock, shBasis, turnLightZ } from './prtt_sh.js';
import {
  MAX_SCENE_BYTES, PRTTError, arrayTexture, concatLayers, declaredBytes, displayTable, dummy2D, expandSharedGlossy,
  gpuLimits, keepLayers, maskTexture,
} from './prtt_textures.js';

export const NAME = 'PRTT_radiance_transfer';
export { MODES, PRTTError };

/** The PRTTMaterial block (8 floats) of a glTF material: the exported preview values, or the glTF's own. */
function materialBlock(source, ext, textures) {
  const m = ext || {};
  const color = source && source.color ? source.color : new THREE.Color(0.8, 0.8, 0.8);
  const base = m.baseColor || [color.r, color.g, color.b];
  const metallic = m.metallic ?? (source && source.metalness !== undefined ? source.metalness : 0.0);
  const roughness = m.roughness ?? (source && source.roughness !== undefined ? source.roughness : 0.5);
  const f0 = m.f0 ?? 0.04;
  const strength = m.normalStrength ?? (source && source.normalScale ? source.normalScale.x : 1.0);
  const flags = (textures.base ? 1 : 0) | (textures.rough ? 2 : 0) | (textures.normal ? 4 : 0);
  return new Float32Array([base[0], base[1], base[2], metallic, roughness, f0, strength, flags]);
}

const UV_NAMES = ['uv', 'uv1', 'uv2', 'uv3'];

/** The largest sun disc PRTT bakes (core/light/sun.py MAX_ANGLE: 30 degrees). */
const MAX_SUN_ANGLE = Math.PI / 6;

/** The root's sun, checked (the file is untrusted): {name, direction, angle, color, strength}. */
function checkSun(sun) {
  const v3 = (a) => Array.isArray(a) && a.length === 3 && a.every(Number.isFinite);
  const n = v3(sun.direction) ? Math.hypot(...sun.direction) : 0;
  if (!(n > 0.999 && n < 1.001)) throw new PRTTError(`${NAME}: the sun's direction must be a unit vector`);
  if (!(Number.isFinite(sun.angle) && sun.angle >= 0 && sun.angle <= MAX_SUN_ANGLE + 1e-9)) {
    throw new PRTTError(`${NAME}: the sun's angle ${sun.angle} is not 0 to ${MAX_SUN_ANGLE.toFixed(4)} radians`);
  }
  if (!(v3(sun.color) && sun.color.every((c) => c >= 0) && Number.isFinite(sun.strength) && sun.strength >= 0)) {
    throw new PRTTError(`${NAME}: the sun's colour and strength must be finite and not negative`);
  }
  return { name: String(sun.name || 'Sun'), direction: sun.direction.map((x) => x / n), angle: sun.angle,
    color: sun.color.slice(), strength: sun.strength };
}

/** A uniform block ``struct`` (shader_source's typedefs) holding ``data`` (a Float32Array of its vec4s). */
function uniformsGroup(struct, data) {
  const group = new THREE.UniformsGroup();
  group.setName(blockName(struct));
  group.add(new THREE.Uniform(data));
  return group;
}

/** The most lamps a set's masks hold (core/light/lamp.py MAX_LAMPS). */
const MAX_LAMPS = 4;

/**
 * The root's lamps, checked (the file is untrusted): [{name, kind, position,
 * radius, power, color, axis, spotSize, spotBlend}] (core/light/lamp.py's conventions).
 */
function checkLamps(lamps) {
  if (!Array.isArray(lamps) || lamps.length < 1 || lamps.length > MAX_LAMPS) {
    throw new PRTTError(`${NAME}: lamps must be a list of 1 to ${MAX_LAMPS}`);
  }
  const v3 = (a) => Array.isArray(a) && a.length === 3 && a.every(Number.isFinite);
  return lamps.map((lp, i) => {
    const what = `${NAME}: lamp ${i}`;
    if (!lp || !['POINT', 'SPOT'].includes(lp.kind)) throw new PRTTError(`${what}: kind must be POINT or SPOT`);
    if (!v3(lp.position) || !v3(lp.axis)) throw new PRTTError(`${what}: position and axis must be 3 finite numbers`);
    const n = Math.hypot(...lp.axis);
    if (!(n > 0.999 && n < 1.001)) throw new PRTTError(`${what}: its axis must be a unit vector`);
    const ok = (x, lo, hi) => Number.isFinite(x) && x >= lo && x <= hi;
    if (!ok(lp.radius, 0, 1e4) || !ok(lp.power, 0, 1e12) || !ok(lp.spotSize, 0, Math.PI) || !ok(lp.spotBlend, 0, 1)
        || !(v3(lp.color) && lp.color.every((c) => c >= 0))) {
      throw new PRTTError(`${what}: radius, power, colour, spotSize and spotBlend must be finite and in range`);
    }
    return { name: String(lp.name || `Lamp ${i}`), kind: lp.kind, position: lp.position.slice(), radius: lp.radius,
      power: lp.power, color: lp.color.slice(), axis: lp.axis.map((x) => x / n), spotSize: lp.spotSize,
      spotBlend: lp.spotBlend };
  });
}

/** The PRTTLamps block of checked lamps (core/preview/pack.lamp_block). */
function lampBlock(lamps, data) {
  data.fill(0);
  data[0] = lamps.length;
  lamps.forEach((lp, i) => {
    const spot = lp.kind === 'SPOT';
    const c = spot ? Math.cos(0.5 * lp.spotSize) : -2;
    const width = (1 - c) * lp.spotBlend;
    const smooth = spot ? (width > 0 ? Math.min(1 / width, 1e20) : 1e20) : 1;
    const I = lp.color.map((x) => x * lp.power / (4 * Math.PI));
    data.set([...lp.position, lp.radius], 4 + 4 * i);
    data.set([...I, smooth], 20 + 4 * i);
    data.set([...lp.axis, c], 36 + 4 * i);
  });
}

/** A PRTT scene: its sets, light, mode and materials; draws with `render`. */
class PRTTScene {
  constructor(ext, limits, sources) {
    this.ext = ext;
    this.bands = ext.sh.bands;
    this.K = ext.sh.coefficients;
    this.limits = limits;
    this.read = sources;
    this.exposure = (ext.display && ext.display.exposure) || 1.0;
    this.display = null;            // {texture, gammaInv, name}: the view transform's table, or sRGB (Standard)
    this.baseLight = ext.light.rgb.map((c) => [c[0], c[1], c[2]]);
    this.light = this.baseLight;
    this.turn = 0;
    this.mode = 'tpfl';
    this.bounces = true;
    this.sets = [];
    this.meshes = [];               // {mesh, set, primitive extension, material source, material ext}
    this.notes = [];
    this.viewData = new Float32Array(24);
    this.viewGroup = uniformsGroup('PRTTView', this.viewData);
    this.lightData = lightBlock(this.light, this.bands);
    this.lightGroup = uniformsGroup('PRTTLight', this.lightData);
    this.relightDirty = true;
    this.sun = null;                // the root's sun, checked (drawn on the sets with a mask)
    this.sunOn = true;
    this.sunData = new Float32Array(8);
    this.sunGroup = uniformsGroup('PRTTSun', this.sunData);
    this.lamps = null;              // the root's lamps, checked (drawn on the sets with their masks)
    this.lampsOn = true;
    this.lampData = new Float32Array(52);
    this.lampGroup = uniformsGroup('PRTTLamps', this.lampData);
    this.dummy = dummy2D();
    this.gaunt = null;
    this.materials = new Map();
    this.prepass = true;           // a depth pre-pass, as the Blender preview's fragment modes
    this.depth = null;
    this.drawn = null;             // {frame, camera} beforeDraw last prepared
  }

  /** Turn the World by ``degrees`` about Z from the export's (no reload). */
  setTurn(degrees) {
    this.turn = degrees;
    this.setLight(this.baseLight, { keepBase: true });
  }

  /** Light the scene by ``L`` (K RGB SH, bake frame), turned by the current turn. */
  setLight(L, { keepBase = false } = {}) {
    if (L.length < this.K) throw new PRTTError(`the light has ${L.length} SH coefficients, the bake ${this.K}`);
    if (!keepBase) this.baseLight = L.slice(0, this.K);
    this.light = this.turn ? turnLightZ(this.baseLight, this.turn) : this.baseLight;
    this.lightData.set(lightBlock(this.light, this.bands));
    this.relightDirty = true;
  }

  /**
   * The sun's colour (linear RGB) and strength (W/m²) live, as a Sun lamp's
   * in Blender (its shadows stay the baked masks); ``on`` false leaves it out.
   */
  setSun({ color, strength, on } = {}) {
    if (!this.sun) throw new PRTTError('this file has no sun: its bake had no Sun lamp');
    if (color !== undefined) {
      if (!(Array.isArray(color) && color.length === 3 && color.every((c) => Number.isFinite(c) && c >= 0))) {
        throw new PRTTError('the sun\'s colour must be 3 finite numbers, not negative');
      }
      this.sun.color = color.slice();
    }
    if (strength !== undefined) {
      if (!(Number.isFinite(strength) && strength >= 0)) throw new PRTTError('the sun\'s strength must be finite, not negative');
      this.sun.strength = strength;
    }
    const d = this.sun.direction, a = this.sun.angle, e = this.sun.strength;
    this.sunData.set([d[0], d[1], d[2], a * a / 16, e * this.sun.color[0], e * this.sun.color[1],
      e * this.sun.color[2], 0]);
    this.relightDirty = true;        // the relightable bounce holds the sun's light too
    if (on !== undefined && Boolean(on) !== this.sunOn) {
      this.sunOn = Boolean(on);
      this.relightDirty = true;
      this.setMode(this.mode);
    }
  }

  /**
   * A lamp's colour (linear RGB) and power (W) live, by its name or index, as
   * in Blender (its shadows stay the baked masks); ``on`` false leaves every lamp out.
   */
  setLamp(which, { color, power, on } = {}) {
    if (!this.lamps) throw new PRTTError('this file has no lamps: its bake had no point or spot lamp');
    const lp = typeof which === 'number' ? this.lamps[which] : this.lamps.find((x) => x.name === which);
    if (!lp) throw new PRTTError(`no lamp ${which}; the file has ${this.lamps.map((x) => x.name).join(', ')}`);
    if (color !== undefined) {
      if (!(Array.isArray(color) && color.length === 3 && color.every((c) => Number.isFinite(c) && c >= 0))) {
        throw new PRTTError('a lamp\'s colour must be 3 finite numbers, not negative');
      }
      lp.color = color.slice();
    }
    if (power !== undefined) {
      if (!(Number.isFinite(power) && power >= 0)) throw new PRTTError('a lamp\'s power must be finite, not negative');
      lp.power = power;
    }
    lampBlock(this.lamps, this.lampData);
    if (on !== undefined && Boolean(on) !== this.lampsOn) {
      this.lampsOn = Boolean(on);
      this.setMode(this.mode);
    }
  }

  /** Switch the shading: 'tpfl' | 'tp' | 'diffuse', with or without the bounce. */
  setMode(mode, { bounces = this.bounces } = {}) {
    if (!MODES.includes(mode)) throw new PRTTError(`unknown mode ${mode}; use one of ${MODES.join(', ')}`);
    this.mode = mode;
    this.bounces = bounces;
    for (const m of this.meshes) m.mesh.material = m.shading = this.surfaceMaterial(m);
  }

  /** Free what this scene put on the GPU: PRTT textures, relight targets, materials. */
  dispose() {
    for (const s of this.sets) {
      s.transfer.dispose();
      if (s.bounce) s.bounce.dispose();
      if (s.sun) s.sun.dispose();
      if (s.lamps) s.lamps.dispose();
      if (s.relight) {
        s.relight.target.dispose();
        s.relight.operator.dispose();
        s.relight.material.dispose();
      }
    }
    for (const mat of this.materials.values()) mat.dispose();
    if (this.depth) this.depth.dispose();
    if (this.gaunt) this.gaunt.tex.dispose();
    this.dummy.dispose();
    for (const g of [this.viewGroup, this.lightGroup, this.sunGroup, this.lampGroup]) g.dispose();
  }

  /** The depth pre-pass material: Blender's (shaders/prtt_depth_*.glsl), the same clip positions. */
  depthMaterial() {
    if (!this.depth) {
      const { vertexShader, fragmentShader } = surfaceSources(depthVariant(), this.read, this.ext.sh.gltfToBakeFrame);
      this.depth = new THREE.RawShaderMaterial({ glslVersion: THREE.GLSL3, vertexShader, fragmentShader,
        colorWrite: false, side: THREE.DoubleSide });
      this.depth.uniformsGroups = [this.viewGroup];
    }
    return this.depth;
  }

  gauntTexture() {
    if (!this.gaunt) {
      const t = gauntTable(this.bands, GAUNT_WIDTH);
      const tex = new THREE.DataTexture(t.data, GAUNT_WIDTH, t.rows, THREE.RGBAFormat, THREE.FloatType);
      tex.minFilter = tex.magFilter = THREE.NearestFilter;
      tex.needsUpdate = true;
      this.gaunt = { tex, nnz: t.nnz };
    }
    return this.gaunt;
  }

  /** The bounce texture of set s under the current light, or null. */
  bounceTexture(s) {
    if (!this.bounces) return null;
    if (s.bounce) return s.bounce;
    if (s.relight) return s.relight.target.texture;
    return null;
  }

  surfaceMaterial(m) {
    const s = this.sets[m.set];
    const bounce = this.bounceTexture(s);
    const triple = this.mode === 'tp';
    const sun = Boolean(this.sunOn && this.sun && s.sun);
    const lamps = Boolean(this.lampsOn && this.lamps && s.lamps);
    const key = `${this.mode}|${m.set}|${!!bounce}|${sun}|${lamps}|${m.matKey}`;
    const cached = this.materials.get(key);
    if (cached) return cached;
    const v = surfaceVariant(this.mode, this.bands, { bounce: !!bounce, display: !!this.display, sun, lamps,
      gauntNnz: triple ? this.gauntTexture().nnz : 0 });
    const units = v.samplers.length;
    if (units > this.limits.maxTextureUnits) {
      throw new PRTTError(`mode ${this.mode} needs ${units} texture units, this browser's MAX_TEXTURE_IMAGE_UNITS `
        + `is ${this.limits.maxTextureUnits}`);
    }
    const { vertexShader, fragmentShader } = surfaceSources(v, this.read, this.ext.sh.gltfToBakeFrame);
    const uniforms = {
      transferTex: { value: s.transfer },
      baseTex: { value: m.textures.base || this.dummy },
      roughTex: { value: m.textures.rough || this.dummy },
      normalTex: { value: m.textures.normal || this.dummy },
    };
    if (bounce) uniforms.bounceTex = { value: bounce };
    if (triple) uniforms.gauntTex = { value: this.gauntTexture().tex };
    if (this.display) uniforms.displayLut = { value: this.display.texture };
    if (sun) uniforms.sunTex = { value: s.sun };
    if (lamps) uniforms.lampTex = { value: s.lamps };
    const mat = new THREE.RawShaderMaterial({
      glslVersion: THREE.GLSL3, vertexShader, fragmentShader, uniforms,
      defines: { PRTT_ROUGHNESS_CHANNEL: 'g' },      // glTF packs roughness in G
      side: THREE.DoubleSide,
    });
    const matGroup = uniformsGroup('PRTTMaterial', m.block);
    mat.uniformsGroups = [this.viewGroup, matGroup, this.lightGroup, ...(sun ? [this.sunGroup] : []),
      ...(lamps ? [this.lampGroup] : [])];
    this.materials.set(key, mat);
    return mat;
  }

  /**
   * The light relightable bounces are relit with: the environment's SH and, with the sun drawn,
   * its SH projection E y_k(l) (shade.sun_sh; PreviewScene.bounce_light in Blender).
   */
  bounceLight() {
    if (!(this.sun && this.sunOn)) return this.light;
    const y = shBasis(this.sun.direction, this.bands, true);
    const E = this.sun.color.map((c) => c * this.sun.strength);
    return this.light.map((c, k) => [c[0] + E[0] * y[k], c[1] + E[1] * y[k], c[2] + E[2] * y[k]]);
  }

  /** Relight every relightable set under the current light (one pass per output layer). */
  relight(renderer) {
    if (!this.relightDirty) return;
    this.relightDirty = false;
    const K4 = shSizes(this.bands)[1];
    const block = relightBlock(this.bounceLight(), this.bands);
    for (const s of this.sets) {
      const r = s.relight;
      if (!r) continue;
      r.block.set(block);
      const prevTarget = renderer.getRenderTarget();
      for (let c = 0; c < 3; c++) {
        for (let q = 0; q < K4; q++) {
          r.material.uniforms.out_colour.value = c;
          r.material.uniforms.out_q.value = q;
          renderer.setRenderTarget(r.target, c * K4 + q);
          renderer.render(r.scene, r.camera);
        }
      }
      renderer.setRenderTarget(prevTarget);
    }
  }

  /**
   * What a frame needs before PRTT's objects draw from ``camera``: the relight passes when the
   * light changed, then the view block. Each PRTT mesh's onBeforeRender calls it (the first one
   * of a frame does the work), so three's own renderer.render(scene, camera) draws PRTT; the
   * relight passes are renders to targets nested in that render, as three's Reflector does.
   */
  beforeDraw(renderer, camera) {
    const frame = renderer.info.render.frame;
    if (this.drawn && this.drawn.frame === frame && this.drawn.camera === camera) return;
    this.relight(renderer);             // a nested render counts a frame: read the count after it
    this.setView(camera);
    this.drawn = { frame: renderer.info.render.frame, camera };
  }

  /**
   * Draw ``scene`` from ``camera`` with a depth pre-pass (``prepass``, as Blender's preview:
   * each pixel shaded once); without it, the same as renderer.render(scene, camera).
   */
  render(renderer, scene, camera) {
    if (!this.prepass) {
      renderer.render(scene, camera);
      return;
    }
    camera.updateMatrixWorld();
    this.beforeDraw(renderer, camera);
    // As Blender's preview: depth first, then each pixel shaded once (LESS_EQUAL on equal depths)
    const depth = this.depthMaterial();
    const autoClear = renderer.autoClear;
    try {
      for (const m of this.meshes) m.mesh.material = depth;
      renderer.render(scene, camera);
      renderer.autoClear = false;
      for (const m of this.meshes) m.mesh.material = m.shading;
      renderer.render(scene, camera);
    } finally {
      renderer.autoClear = autoClear;
      for (const m of this.meshes) m.mesh.material = m.shading;
    }
  }

  /** The view block (the clip transform from the bake frame, the eye, exposure, K, gamma) of ``camera``. */
  setView(camera) {
    const toBake = new THREE.Matrix4();
    const g = this.ext.sh.gltfToBakeFrame;
    toBake.set(g[0][0], g[0][1], g[0][2], 0, g[1][0], g[1][1], g[1][2], 0, g[2][0], g[2][1], g[2][2], 0, 0, 0, 0, 1);
    const vp = new THREE.Matrix4().multiplyMatrices(camera.projectionMatrix, camera.matrixWorldInverse)
      .multiply(toBake.clone().invert());
    this.viewData.set(vp.elements, 0);                    // column-major, as GLSL reads it
    const eye = new THREE.Vector3().setFromMatrixPosition(camera.matrixWorld).applyMatrix4(toBake);
    this.viewData.set([eye.x, eye.y, eye.z, 1.0], 16);
    this.viewData.set([this.exposure, 0.0, this.K, this.display ? this.display.gammaInv : 0.0], 20);
  }
}

/** The relight machinery of one set: operator texture, target array, quad pass. */
function relightPass(operator, width, height, K4, glossyBands, bands, read, limits) {
  if (!limits.floatRenderTarget) {
    throw new PRTTError('relightable bounces need float render targets (EXT_color_buffer_float), which this '
      + 'browser lacks; view without bounces (&bounces=0)');
  }
  // float32 as Blender's relight pass writes; half floats where float32 cannot be filtered
  const target = new THREE.WebGLArrayRenderTarget(width, height, 3 * K4, {
    type: limits.floatLinear ? THREE.FloatType : THREE.HalfFloatType, format: THREE.RGBAFormat, depthBuffer: false,
    minFilter: THREE.LinearFilter, magFilter: THREE.LinearFilter, generateMipmaps: false,
  });
  target.texture.colorSpace = THREE.NoColorSpace;
  const v = relightVariant(bands, glossyBands);
  const { vertexShader, fragmentShader } = relightSources(v, read);
  const block = new Float32Array(3 * K4 * 4);
  const group = uniformsGroup('PRTTRelight', block);
  const material = new THREE.RawShaderMaterial({
    glslVersion: THREE.GLSL3, vertexShader, fragmentShader, depthTest: false, depthWrite: false,
    uniforms: { relightTex: { value: operator }, out_colour: { value: 0 }, out_q: { value: 0 } },
  });
  material.uniformsGroups = [group];
  const quad = new THREE.BufferGeometry();
  quad.setAttribute('pos', new THREE.BufferAttribute(new Float32Array([-1, -1, 1, -1, -1, 1, 1, 1]), 2));
  quad.setAttribute('position', new THREE.BufferAttribute(new Float32Array(12), 3));
  quad.setIndex([0, 1, 2, 2, 1, 3]);
  const mesh = new THREE.Mesh(quad, material);
  mesh.frustumCulled = false;
  const scene = new THREE.Scene();
  scene.add(mesh);
  return { target, material, block, scene, camera: new THREE.OrthographicCamera(), operator };
}

/**
 * An instance's PRTT UVs in its tile of the set's texture (docs/gltf.md):
 * tile = [columns, rows, column, row, inset], in Blender's UV frame
 * u_t = (column + inset + u (1 - 2 inset)) / columns, v_t likewise with rows,
 * applied here to glTF's v' = 1 - v. A new attribute: the mesh's own UVs are
 * shared with the other instances.
 */
function tiledUvs(uv, tile, name) {
  const ok = Array.isArray(tile) && tile.length === 5 && tile.every(Number.isFinite)
    && Number.isInteger(tile[0]) && Number.isInteger(tile[1]) && tile[0] >= 1 && tile[1] >= 1
    && Number.isInteger(tile[2]) && Number.isInteger(tile[3]) && tile[2] >= 0 && tile[2] < tile[0]
    && tile[3] >= 0 && tile[3] < tile[1] && tile[4] >= 0 && tile[4] < 0.5;
  if (!ok) throw new PRTTError(`node ${name}: tile ${JSON.stringify(tile)} is not [columns, rows, column, row, inset]`);
  const [gx, gy, col, row, inset] = tile;
  const scale = 1 - 2 * inset;
  const out = new Float32Array(uv.count * 2);
  for (let i = 0; i < uv.count; i++) {
    const u = uv.getX(i), v = 1 - uv.getY(i);
    out[2 * i] = (col + inset + u * scale) / gx;
    out[2 * i + 1] = 1 - (row + inset + v * scale) / gy;
  }
  return new THREE.BufferAttribute(out, 2);
}

/** GLTFLoader plugin: gltf.userData.prtt becomes a PRTTScene (or null without the extension). */
export class PRTTLoaderPlugin {
  constructor(parser, { renderer, mode = 'tpfl', bounces = true, sun = true, shaderBase } = {}) {
    this.name = NAME;
    this.parser = parser;
    this.renderer = renderer;
    this.mode = mode;
    this.bounces = bounces;
    this.sunOn = sun;
    this.shaderBase = shaderBase;
  }

  async afterRoot(gltf) {
    const parser = this.parser;
    const json = parser.json;
    let ext = json.extensions && json.extensions[NAME];
    gltf.userData.prtt = null;
    if (!ext) return;
    if (!this.renderer) throw new PRTTError('PRTTLoaderPlugin needs { renderer } (for the browser\'s limits)');
    const limits = gpuLimits(this.renderer);
    const fileBands = ext.sh && ext.sh.bands;
    if (!(Number.isInteger(fileBands) && fileBands >= 1 && fileBands <= 16)
        || ext.sh.coefficients !== fileBands * fileBands) {
      throw new PRTTError(`${NAME}: ${ext.sh && ext.sh.coefficients} coefficients for ${fileBands} bands; `
        + 'PRTT writes K = bands^2 coefficients, 1 to 16 bands');
    }
    const [fileK, fileK4] = shSizes(fileBands);
    if (!Array.isArray(ext.light && ext.light.rgb) || ext.light.rgb.length !== fileK
        || !ext.light.rgb.every((c) => Array.isArray(c) && c.length === 3 && c.every(Number.isFinite))) {
      throw new PRTTError(`${NAME}: the light must be ${fileK} finite RGB coefficients, the file has `
        + `${ext.light && ext.light.rgb && ext.light.rgb.length}`);
    }
    // Fewer bands where the browser cannot hold the file's: the light block
    // (TPFL's M(L)) grows as bands^4; the low bands of every texture still apply.
    const blockBytes = (b) => 16 * (3 * b * b * Math.ceil(b * b / 4) + b * b);
    let bands = Math.min(fileBands, MAX_PREVIEW_BANDS);
    while (bands > 1 && blockBytes(bands) > limits.maxUniformBlockSize) bands -= 1;
    const fallback = [];
    if (bands < fileBands) {
      fallback.push(`drawn with ${bands} of the file's ${fileBands} SH bands: ${fileBands} bands need a `
        + `${blockBytes(fileBands)}-byte light block (this browser's MAX_UNIFORM_BLOCK_SIZE is `
        + `${limits.maxUniformBlockSize}; the viewer draws at most ${MAX_PREVIEW_BANDS})`);
    }
    const [K, K4] = shSizes(bands);
    const ext0 = ext;
    ext = { ...ext0, sh: { ...ext0.sh, bands, coefficients: K }, light: { ...ext0.light, rgb: ext0.light.rgb.slice(0, K) } };
    const files = [...new Set([...surfaceVariant('tpfl', bands).vertexFiles,
      ...surfaceVariant('tpfl', bands, { display: true }).fragmentFiles, ...relightVariant(bands, 1).vertexFiles,
      ...relightVariant(bands, 1).fragmentFiles, ...depthVariant().vertexFiles, ...depthVariant().fragmentFiles])];
    const read = await fetchSources(files, this.shaderBase);
    const prtt = new PRTTScene(ext, limits, read);
    if (ext.sun) prtt.sun = checkSun(ext.sun);
    if (ext.lamps) prtt.lamps = checkLamps(ext.lamps);
    const planned = declaredBytes(ext.sets);
    if (planned > MAX_SCENE_BYTES) {
      throw new PRTTError(`the file's textures unpack to ${Math.round(planned / 2 ** 20)} MiB, over the viewer's `
        + `${MAX_SCENE_BYTES / 2 ** 20} MiB for a whole scene; export a bake at a lower resolution or with `
        + 'fewer bands (nothing was decoded)');
    }
    const zstd = new ZSTDDecoder();
    await zstd.init();
    prtt.notes.push(...fallback);
    // A payload's bytes, once the extension says where they are and how large they make a texture.
    const placed = async (p, what) => {
      if (!p || !Number.isInteger(p.bufferView) || !Number.isInteger(p.width) || !Number.isInteger(p.height)
          || p.width < 1 || p.height < 1) {
        throw new PRTTError(`${what}: the extension does not say where and how large it is`);
      }
      return new Uint8Array(await parser.getDependency('bufferView', p.bufferView));
    };
    const payload = async (p, what, layers) => arrayTexture(await placed(p, what), zstd, what,
      { layers, width: p.width, height: p.height, encoding: p.encoding, scale: p.scale, offset: p.offset }, limits);
    for (const s of ext.sets) {
      const transfer = await payload(s.transfer, `set ${s.name} transfer`, fileK4);
      const entry = { name: s.name, transfer: keepLayers(transfer, 1, fileK4, K4) };
      if (s.sun && prtt.sun) {
        const what = `set ${s.name} sun mask`;
        entry.sun = maskTexture(await placed(s.sun, what), zstd, what, s.sun, limits);
      }
      if (s.lamps && prtt.lamps) {
        const m = s.lamps, what = `set ${s.name} lamp masks`;
        const bytes = await placed(m, what);
        if (m.lamps !== prtt.lamps.length) {
          throw new PRTTError(`${what}: ${m.lamps} lamps, the file has ${prtt.lamps.length}`);
        }
        entry.lamps = maskTexture(bytes, zstd, what,
          { ...m, format: m.format === 'RGBA8' ? 'RGBA8' : `${m.format} (lamp masks are RGBA8)` }, limits);
      }
      if (s.bounce) {
        entry.bounce = keepLayers(await payload(s.bounce, `set ${s.name} bounce`, 3 * fileK4), 3, fileK4, K4);
      } else if (s.relightDC) {
        const parts = [keepLayers(await payload(s.relightDC, `set ${s.name} relightable bounce`, 3 * fileK4),
          3, fileK4, K4)];
        let gb = 0;
        if (s.relightGlossy) {
          gb = s.relightGlossy.glossyBands;
          if (!(Number.isInteger(gb) && gb >= 1 && gb <= fileBands)) {
            throw new PRTTError(`set ${s.name}: relightGlossy has ${gb} glossy bands, the file ${fileBands}`);
          }
          const kg = gb * gb, kg4 = Math.ceil(kg / 4);
          const glossyLayers = 3 * (kg - 1) * kg4;
          if (gb > bands) {
            prtt.notes.push(`set ${s.name}: the bounce's glossy rows (${gb} bands) left out: drawn with ${bands}`);
            gb = 0;
          } else if (3 * K4 + glossyLayers > limits.maxArrayLayers) {
            prtt.notes.push(`set ${s.name}: the bounce's glossy rows left out (diffuse bounce only): they need `
              + `${3 * K4 + glossyLayers} layers, over this browser's MAX_ARRAY_TEXTURE_LAYERS `
              + `(${limits.maxArrayLayers})`);
            gb = 0;
          } else if (s.relightGlossy.glossyColour === 'shared') {
            const shared = await payload(s.relightGlossy, `set ${s.name} relightable glossy rows`,
              (kg - 1) * kg4);
            parts.push(expandSharedGlossy(parts[0], K4, shared, kg));
          } else {
            parts.push(await payload(s.relightGlossy, `set ${s.name} relightable glossy rows`, glossyLayers));
          }
        }
        // the bounce's own grid (the bake's bounce grid: coarser than the transfer where islands allow)
        const bw = s.relightDC.width, bh = s.relightDC.height;
        if (parts.some((p) => p.image.width !== bw || p.image.height !== bh)) {
          throw new PRTTError(`set ${s.name}: its relightable bounce's DC and glossy rows differ in size`);
        }
        entry.relight = relightPass(concatLayers(parts, bw, bh), bw, bh, K4, gb, bands, read, limits);
      }
      prtt.sets.push(entry);
    }
    if (ext.display && ext.display.table) {
      const t = ext.display.table;
      if (!Number.isInteger(t.bufferView)) throw new PRTTError('display table: the extension does not say where it is');
      prtt.display = displayTable(ext.display, new Uint8Array(await parser.getDependency('bufferView', t.bufferView)),
        zstd);
    }
    const nodes = json.nodes || [];
    const meshes = json.meshes || [];
    const materials = json.materials || [];
    const todo = new Map();          // mesh -> its node's extension; the deepest baked node wins
    gltf.scene.traverse((obj) => {
      const assoc = parser.associations.get(obj);
      if (!assoc || assoc.nodes === undefined) return;
      const nodeExt = (nodes[assoc.nodes].extensions || {})[NAME];
      if (!nodeExt) return;
      if (!(nodeExt.set >= 0 && nodeExt.set < prtt.sets.length)) {
        throw new PRTTError(`node ${nodes[assoc.nodes].name}: set ${nodeExt.set} is not in the file`);
      }
      obj.traverse((m) => { if (m.isMesh) todo.set(m, nodeExt); });   // pre-order: a baked child overrides
    });
    for (const [m, nodeExt] of todo) {
      const a = parser.associations.get(m) || {};
      const prim = meshes[a.meshes] && meshes[a.meshes].primitives[a.primitives || 0];
      const primExt = prim && (prim.extensions || {})[NAME];
      if (!primExt) continue;
      const geometry = m.geometry;
      let uv = geometry.getAttribute(UV_NAMES[primExt.texCoord] || `uv${primExt.texCoord}`);
      if (!uv) throw new PRTTError(`mesh ${m.name}: no TEXCOORD_${primExt.texCoord} (its PRTT UVs)`);
      if (nodeExt.tile) uv = tiledUvs(uv, nodeExt.tile, m.name);
      const source = m.material;
      const matIndex = prim.material;
      // no material: the preview's default (the root's defaultMaterial), not glTF's default
      // (metallic 1), which would draw the object black; files without it: the glTF's
      const matExt = matIndex !== undefined ? ((materials[matIndex] || {}).extensions || {})[NAME]
        : ext.defaultMaterial;
      const textures = {};
      if (!matExt || matExt.baseColorTexture) textures.base = source.map || null;
      if (!matExt || matExt.roughnessTexture) textures.rough = source.roughnessMap || null;
      if (!matExt || matExt.normalTexture) textures.normal = source.normalMap || null;
      for (const [k, flag] of [['base', 'baseColorTexture'], ['rough', 'roughnessTexture'],
        ['normal', 'normalTexture']]) {
        if (matExt && matExt[flag] && !textures[k]) {
          prtt.notes.push(`material ${source.name}: its ${flag} is not in the glTF; drawn with its constant value`);
        }
      }
      const channel = (t) => (t ? t.channel || 0 : null);
      const muvChannel = channel(textures.base) ?? channel(textures.rough) ?? 0;
      if (textures.base && textures.rough && channel(textures.base) !== channel(textures.rough)) {
        prtt.notes.push(`material ${source.name}: base colour and roughness use different UV maps; roughness `
          + 'drawn with the base colour\'s');
      }
      for (const t of [textures.base, textures.rough, textures.normal]) {
        if (t && (t.offset.x || t.offset.y || t.repeat.x !== 1 || t.repeat.y !== 1 || t.rotation)) {
          prtt.notes.push(`material ${source.name}: a texture transform is not applied by the PRTT viewer`);
        }
      }
      const g = new THREE.BufferGeometry();
      const attr = (name) => geometry.getAttribute(name);
      g.setAttribute('position', attr('position'));
      g.setAttribute('pos', attr('position'));
      g.setAttribute('nor', attr('normal'));
      g.setAttribute('uv', uv);
      g.setAttribute('muv', attr(UV_NAMES[muvChannel]) || uv);
      g.setAttribute('nuv', attr(UV_NAMES[channel(textures.normal) ?? muvChannel]) || uv);
      const tan = attr('tangent');
      if (tan) g.setAttribute('tan', tan);
      else g.setAttribute('tan', new THREE.BufferAttribute(new Float32Array(4 * attr('position').count), 4));
      if (textures.normal && !tan) {
        prtt.notes.push(`mesh ${m.name}: its normal map needs tangents (export with a normal map adds them)`);
        textures.normal = null;
      }
      if (geometry.index) g.setIndex(geometry.index);
      g.groups = geometry.groups;
      m.geometry = g;
      const block = materialBlock(source, matExt, textures);
      prtt.meshes.push({ mesh: m, set: nodeExt.set, textures, block,
        matKey: `${matIndex}|${m.uuid}` });
      m.onBeforeRender = (renderer, _scene, camera) => prtt.beforeDraw(renderer, camera);
    }
    if (prtt.sun) {
      prtt.sunOn = this.sunOn;
      prtt.setSun();                 // the block from the file's colour and strength
    }
    if (prtt.lamps) lampBlock(prtt.lamps, prtt.lampData);
    prtt.setMode(this.mode, { bounces: this.bounces });
    gltf.userData.prtt = prtt;
  }
}

/**
 * The bytes of a .glb at `url`, with onProgress(received, total) as they come
 * (total 0 when the server does not say), checked whole: a file cut short is
 * a PRTTError saying so and how much arrived, not the parser's "Invalid typed
 * array length".
 */
export async function fetchGlb(url, onProgress = null) {
  let res;
  try {
    res = await fetch(url);
  } catch (e) {
    const local = typeof location !== 'undefined' && location.protocol === 'file:';
    throw new PRTTError(local ? `${url}: a page opened from file:// cannot read files; serve the folder ` +
      '(python3 -m http.server) and open it over http://' : `${url}: ${e.message}`);
  }
  if (!res.ok) throw new PRTTError(`${url}: HTTP ${res.status} ${res.statusText}`);
  const total = Number(res.headers.get('Content-Length') || 0);
  const parts = [];
  let got = 0;
  if (res.body && res.body.getReader) {
    const reader = res.body.getReader();
    for (;;) {
      const { done, value } = await reader.read();
      if (done) break;
      parts.push(value);
      got += value.byteLength;
      if (onProgress) onProgress(got, total);
    }
  } else {
    const b = new Uint8Array(await res.arrayBuffer());
    parts.push(b);
    got = b.byteLength;
  }
  const bytes = new Uint8Array(got);
  let at = 0;
  for (const p of parts) { bytes.set(p, at); at += p.byteLength; }
  return checkGlb(bytes.buffer, url);
}

/** `buffer` if it holds a whole .glb (its magic, and as many bytes as its header declares), else a PRTTError naming `name`. */
export function checkGlb(buffer, name = 'the file') {
  const n = buffer.byteLength;
  if (n < 12) throw new PRTTError(`${name}: ${n} bytes, not a .glb (truncated?)`);
  const dv = new DataView(buffer);
  if (dv.getUint32(0, true) !== 0x46546C67) throw new PRTTError(`${name}: not a .glb (no glTF header)`);
  const declared = dv.getUint32(8, true);
  if (n < declared) {
    throw new PRTTError(`${name}: truncated .glb: ${n.toLocaleString('en')} of ${declared.toLocaleString('en')} ` +
      'bytes arrived; copy or download it again');
  }
  return buffer;
}

/**
 * Load a PRTT .glb with a renderer: returns {gltf, scene, camera, prtt, ext}.
 * The title-bar contract of the page (index.html) builds on this.
 * `url`: an address (fetched, onProgress(received, total) as it comes) or an ArrayBuffer.
 */
export async function loadPRTT(url, renderer, { turn = 0, mode = 'tpfl', bounces = true, sun = true,
  onProgress = null } = {}) {
  const { GLTFLoader } = await import('three/addons/loaders/GLTFLoader.js');
  const loader = new GLTFLoader();
  loader.register((parser) => new PRTTLoaderPlugin(parser, { renderer, mode, bounces, sun }));
  const bytes = url instanceof ArrayBuffer ? checkGlb(url) : await fetchGlb(url, onProgress);
  const here = typeof location !== 'undefined' ? location.href : undefined;
  const base = url instanceof ArrayBuffer ? '' : new URL('.', new URL(url, here)).href;
  const gltf = await loader.parseAsync(bytes, base);
  const prtt = gltf.userData.prtt;
  if (prtt && turn) prtt.setTurn(turn);
  return { gltf, scene: gltf.scene, camera: gltf.cameras[0] || null, prtt, ext: prtt ? prtt.ext : null };
}

