// PRTT's web viewer: a .glb exported by `prtt export` (docs/gltf.md), drawn
// with three.js, its PRTT_radiance_transfer data shading each baked object:
// diffuse PRT per pixel, radiance = albedo / pi * (sum_k T_k(uv) L_k + the
// relightable bounce sqrt(4 pi) sum_k DC_k(uv) L_k), the transfer T read from
// the set's KTX2 array texture (RGBA16F, coefficient k in layer k / 4,
// channel k % 4) at the object's PRTT UVs, L the light's SH.
// The same formula as the Blender preview's diffuse mode (shaders/prtt_shade.glsl).
import * as THREE from 'three';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { ZSTDDecoder } from 'three/addons/libs/zstddec.module.js';
import { read as readKTX2 } from 'ktx-parse';

export const NAME = 'PRTT_radiance_transfer';
const VK_FORMAT_R16G16B16A16_SFLOAT = 97;

/** A set's transfer texture from its KTX2 bytes (checked: the one format PRTT writes). */
function transferTexture(bytes, zstd, what) {
  const c = readKTX2(bytes);
  if (c.vkFormat !== VK_FORMAT_R16G16B16A16_SFLOAT || c.layerCount < 1 || c.levels.length < 1) {
    throw new Error(`${what}: not an RGBA16F array texture (vkFormat ${c.vkFormat})`);
  }
  const level = c.levels[0];
  let data = level.levelData;
  if (c.supercompressionScheme === 2) data = zstd.decode(data, level.uncompressedByteLength);
  else if (c.supercompressionScheme !== 0) throw new Error(`${what}: supercompression ${c.supercompressionScheme}`);
  const want = c.pixelWidth * c.pixelHeight * c.layerCount * 8;
  if (data.byteLength !== want) throw new Error(`${what}: ${data.byteLength} bytes, ${want} expected`);
  const half = new Uint16Array(data.buffer.slice(data.byteOffset, data.byteOffset + data.byteLength));
  const tex = new THREE.DataArrayTexture(half, c.pixelWidth, c.pixelHeight, c.layerCount);
  tex.type = THREE.HalfFloatType;
  tex.format = THREE.RGBAFormat;
  tex.minFilter = tex.magFilter = THREE.LinearFilter;
  tex.wrapS = tex.wrapT = THREE.ClampToEdgeWrapping;
  tex.generateMipmaps = false;
  tex.flipY = false;                 // the KTX2's first row is glTF's v = 0
  tex.colorSpace = THREE.NoColorSpace;
  tex.needsUpdate = true;
  return tex;
}

const VERTEX = /* glsl */ `
in vec2 prttUv;
out vec2 vUv;
void main() {
  vUv = prttUv;
  gl_Position = projectionMatrix * modelViewMatrix * vec4(position, 1.0);
}`;

const FRAGMENT = /* glsl */ `
precision highp float;
precision highp sampler2DArray;
uniform sampler2DArray transfer;
#ifdef BOUNCE
uniform sampler2DArray relightDC;   // colour c's DC rows from layer c * LAYERS
#endif
uniform vec3 light[K];
uniform vec3 albedo;
uniform float exposure;
in vec2 vUv;
out highp vec4 fragColor;   // GLSL3: three declares no output of its own
vec3 srgb(vec3 c) {
  c = clamp(c, 0.0, 1.0);
  return mix(12.92 * c, 1.055 * pow(c, vec3(1.0 / 2.4)) - 0.055, step(vec3(0.0031308), c));
}
void main() {
  vec3 e = vec3(0.0);
  for (int q = 0; q < LAYERS; q++) {
    vec4 t = textureLod(transfer, vec3(vUv, float(q)), 0.0);
    for (int c = 0; c < 4; c++) {
      int k = 4 * q + c;
      if (k < K) e += t[c] * light[k];
    }
  }
#ifdef BOUNCE
  // the relightable bounce's diffuse radiance: sqrt(4 pi) sum_i DC_c,i L_c,i
  vec3 dc = vec3(0.0);
  for (int q = 0; q < LAYERS; q++) {
    vec4 r = textureLod(relightDC, vec3(vUv, float(q)), 0.0);
    vec4 g = textureLod(relightDC, vec3(vUv, float(q + LAYERS)), 0.0);
    vec4 b = textureLod(relightDC, vec3(vUv, float(q + 2 * LAYERS)), 0.0);
    for (int c = 0; c < 4; c++) {
      int k = 4 * q + c;
      if (k < K) dc += vec3(r[c] * light[k].r, g[c] * light[k].g, b[c] * light[k].b);
    }
  }
  e += 3.5449077018110318 * dc;
#endif
  fragColor = vec4(srgb(max(albedo / 3.14159265358979 * e, vec3(0.0)) * exposure), 1.0);
}`;

function prttMaterial(tex, bounce, light, K, layers, source) {
  const color = source && source.color ? source.color.clone() : new THREE.Color(0.8, 0.8, 0.8);
  const metal = source && source.metalness !== undefined ? source.metalness : 0.0;
  return new THREE.ShaderMaterial({
    glslVersion: THREE.GLSL3,
    defines: bounce ? { K, LAYERS: layers, BOUNCE: 1 } : { K, LAYERS: layers },
    uniforms: {
      transfer: { value: tex },
      relightDC: { value: bounce },
      light: { value: light },
      albedo: { value: new THREE.Vector3(color.r, color.g, color.b).multiplyScalar(1.0 - metal) },
      exposure: { value: 1.0 },
    },
    vertexShader: VERTEX,
    fragmentShader: FRAGMENT,
  });
}

/**
 * The light's SH (K RGB coefficients, k = l*l + l + m, bake frame, Z up) as
 * the World turned by ``degrees`` about Z sees it: what Blender's preview
 * shows when the World's Mapping node has that Z rotation (its lookups turn
 * by the angle, the environment the other way). A rotation about Z mixes each
 * band's (m, -m) pairs: c'(l, m) = cos(m a) c(l, m) + sin(m a) c(l, -m),
 * c'(l, -m) = -sin(m a) c(l, m) + cos(m a) c(l, -m).
 */
export function turnLight(light, degrees) {
  const a = degrees * Math.PI / 180;
  const out = light.map((v) => v.clone());
  const bands = Math.round(Math.sqrt(light.length));
  for (let l = 1; l < bands; l++) {
    for (let m = 1; m <= l; m++) {
      const p = l * l + l + m, n = l * l + l - m;
      const c = Math.cos(m * a), s = Math.sin(m * a);
      out[p] = light[p].clone().multiplyScalar(c).addScaledVector(light[n], s);
      out[n] = light[n].clone().multiplyScalar(c).addScaledVector(light[p], -s);
    }
  }
  return out;
}

/** Load a PRTT .glb; returns {scene, camera, ext, shaded, setTurn} (shaded: meshes given
 * PRTT materials; setTurn(degrees) turns the light of all of them, no reload).
 * ``turn``: degrees the World is turned about Z from the export's (turnLight). */
export async function loadPRTT(url, { turn = 0, useBounces = true } = {}) {
  const gltf = await new GLTFLoader().loadAsync(url);
  const parser = gltf.parser;
  const ext = parser.json.extensions && parser.json.extensions[NAME];
  if (!ext) throw new Error(`${url}: no ${NAME} extension (export it with prtt export)`);
  const zstd = new ZSTDDecoder();
  await zstd.init();
  const K = ext.sh.coefficients;
  const baseLight = ext.light.rgb.map((c) => new THREE.Vector3(c[0], c[1], c[2]));
  const light = turnLight(baseLight, turn);
  const sets = [], bounces = [];
  for (const s of ext.sets) {
    const buf = await parser.getDependency('bufferView', s.transfer.bufferView);
    sets.push(transferTexture(new Uint8Array(buf), zstd, `set ${s.name}`));
    if (s.relightDC && useBounces) {
      const rb = await parser.getDependency('bufferView', s.relightDC.bufferView);
      bounces.push(transferTexture(new Uint8Array(rb), zstd, `set ${s.name} bounce`));
    } else {
      bounces.push(null);
    }
  }
  const nodes = parser.json.nodes || [];
  const meshes = parser.json.meshes || [];
  let shaded = 0;
  gltf.scene.traverse((obj) => {
    const assoc = parser.associations.get(obj);
    if (!assoc || assoc.nodes === undefined) return;
    const nodeExt = (nodes[assoc.nodes].extensions || {})[NAME];
    if (!nodeExt) return;
    const tex = sets[nodeExt.set], bounce = bounces[nodeExt.set];
    obj.traverse((m) => {
      if (!m.isMesh) return;
      const a = parser.associations.get(m) || {};
      const prim = meshes[a.meshes] && meshes[a.meshes].primitives[a.primitives || 0];
      const primExt = prim && (prim.extensions || {})[NAME];
      if (!primExt) return;
      const name = primExt.texCoord === 0 ? 'uv' : `uv${primExt.texCoord}`;
      const uv = m.geometry.getAttribute(name);
      if (!uv) throw new Error(`mesh ${m.name}: no TEXCOORD_${primExt.texCoord}`);
      m.geometry.setAttribute('prttUv', uv);
      m.material = prttMaterial(tex, bounce, light, K, tex.image.depth, m.material);
      shaded += 1;
    });
  });
  const camera = gltf.cameras[0] || null;
  /** Turn the World to ``degrees`` from the export's: every PRTT material's light at once. */
  const setTurn = (degrees) => {
    const turned = turnLight(baseLight, degrees);
    for (let k = 0; k < light.length; k++) light[k].copy(turned[k]);
  };
  return { scene: gltf.scene, camera, ext, shaded, setTurn };
}
