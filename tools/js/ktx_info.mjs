// Parse a KTX2 file with ktx-parse (an independent reader) and print what it
// found as JSON: header, DFD, key/value data, and each level's bytes as hex
// sha256 (after zstd, which ktx-parse leaves to the caller, the test decodes).
import { read } from 'ktx-parse';
import { readFileSync } from 'node:fs';
import { createHash } from 'node:crypto';

const c = read(new Uint8Array(readFileSync(process.argv[2])));
const kv = {};
for (const [k, v] of Object.entries(c.keyValue)) kv[k] = typeof v === 'string' ? v : Buffer.from(v).toString('utf8').replace(/\0+$/, '');
const out = {
  vkFormat: c.vkFormat, typeSize: c.typeSize, pixelWidth: c.pixelWidth, pixelHeight: c.pixelHeight,
  pixelDepth: c.pixelDepth, layerCount: c.layerCount, faceCount: c.faceCount,
  supercompressionScheme: c.supercompressionScheme,
  dfd: c.dataFormatDescriptor.map((d) => ({
    colorModel: d.colorModel, colorPrimaries: d.colorPrimaries, transferFunction: d.transferFunction,
    flags: d.flags, bytesPlane: Array.from(d.bytesPlane), texelBlockDimension: Array.from(d.texelBlockDimension),
    samples: d.samples.map((s) => ({ bitOffset: s.bitOffset, bitLength: s.bitLength, channelType: s.channelType,
      lower: s.sampleLower, upper: s.sampleUpper })),
  })),
  keyValue: kv,
  levels: c.levels.map((l) => ({ bytes: l.levelData.byteLength, uncompressed: l.uncompressedByteLength,
    sha256: createHash('sha256').update(l.levelData).digest('hex') })),
};
console.log(JSON.stringify(out));
