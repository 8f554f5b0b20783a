// Read a KTX2 file with ktx-parse and write it back with ktx-parse's own
// writer (keeping KTXwriter): the bytes a second implementation lays out for
// the same container, which the test compares with PRTT's file.
import { read, write } from 'ktx-parse';
import { readFileSync, writeFileSync } from 'node:fs';

writeFileSync(process.argv[3], write(read(new Uint8Array(readFileSync(process.argv[2]))), { keepWriter: true }));
