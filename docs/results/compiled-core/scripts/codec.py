"""Lab: CPU of codecs on one recorded episode's chunk payloads (the uncompressed records), per simulated second.

    lc-record --scenario paper --driver rule --episodes 1 --seed 1 --out runs/rec
    python docs/results/compiled-core/scripts/codec.py runs/rec/paper_rule_s0000001.mcap 68.7
"""
import sys
import time

import lz4.frame
import zstandard
from mcap.records import Chunk
from mcap.stream_reader import StreamReader

path, sim_s = sys.argv[1], float(sys.argv[2])
raw = []
with open(path, "rb") as f:
    for rec in StreamReader(f, emit_chunks=True).records:
        if isinstance(rec, Chunk):
            raw.append(zstandard.ZstdDecompressor().decompress(rec.data, max_output_size=rec.uncompressed_size))
total = sum(map(len, raw))
print(f"{len(raw)} chunks, {total/1e6:.1f} MB uncompressed, {total/sim_s/1e3:.0f} KB per simulated s")


def bench(name, fn, reps=5):
    best, size = 1e9, 0
    for _ in range(reps):
        t = time.process_time()
        size = sum(len(fn(c)) for c in raw)
        best = min(best, time.process_time() - t)
    print(f"{name:14s} {best*1e3:6.1f} ms  {best*1e3/sim_s:.3f} ms per sim s  {size/1e6:5.2f} MB")


for lvl in (3, 1, -1, -3, -7, -15, -50):
    c = zstandard.ZstdCompressor(level=lvl)
    bench(f"zstd {lvl}", c.compress)
bench("lz4 (frame)", lz4.frame.compress)
bench("memcpy", lambda b: bytearray(b))
