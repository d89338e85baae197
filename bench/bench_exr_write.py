"""How long writing one sample's EXR takes, and how large it is, per codec and ZIP level.

Reads real samples of a dataset (their channels, as the generator hands them to OpenEXR) and
writes each again in turns, so every setting sees the same data under the same load:

    python bench/bench_exr_write.py data/intrinsics --json results/bench/exr_write.json

ZIP levels go through OpenEXR's process-wide default (`exr_set_default_zip_compression_level`,
exported by the Python binding's shared object): the binding stores a header's
`zipCompressionLevel` without applying it. -1 is the library's own default, which the generator
uses.
"""
from __future__ import annotations

import argparse
import ctypes
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from blender_gen.dataset import read_exr_channels, read_manifest  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", type=Path, help="a dataset folder (iae-gen intrinsics or pbr)")
    ap.add_argument("--samples", type=int, default=4, help="samples of the set to write (default 4)")
    ap.add_argument("--repeats", type=int, default=15, help="writes per sample and setting (default 15)")
    ap.add_argument("--rounds", type=int, default=2, help="passes over all settings (default 2)")
    ap.add_argument("--zip-levels", type=int, nargs="+", default=[-1, 1, 2, 9])
    ap.add_argument("--codecs", nargs="+", default=["PIZ", "RLE", "NO"],
                    help="other codecs, by OpenEXR's names without _COMPRESSION")
    ap.add_argument("--json", type=Path, help="write the figures here as well")
    args = ap.parse_args()

    import OpenEXR

    rows = read_manifest(args.dataset / "manifest.jsonl")[: args.samples]
    if not rows:
        sys.exit(f"{args.dataset}: no finished samples in manifest.jsonl")
    samples = [read_exr_channels(args.dataset / r["file"]) for r in rows]
    shape = next(iter(samples[0].values())).shape
    lib = ctypes.CDLL(OpenEXR.__file__)
    settings = [("ZIP", lvl) for lvl in args.zip_levels] + [(c, None) for c in args.codecs]
    times: dict[str, list[float]] = {}
    sizes: dict[str, list[int]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "sample.exr"
        for _ in range(args.rounds):
            for codec, level in settings:
                key = codec if level is None else f"ZIP level {level}"
                lib.exr_set_default_zip_compression_level(ctypes.c_int(-1 if level is None else level))
                header = {"compression": getattr(OpenEXR, f"{codec}_COMPRESSION"), "type": OpenEXR.scanlineimage}
                for channels in samples:
                    for _ in range(args.repeats):
                        t = time.perf_counter()
                        with OpenEXR.File(header, channels) as f:
                            f.write(str(out))
                        times.setdefault(key, []).append(time.perf_counter() - t)
                    sizes.setdefault(key, []).append(out.stat().st_size)
    result = {"dataset": str(args.dataset), "samples": len(samples), "channels": len(samples[0]),
              "size": f"{shape[1]}x{shape[0]}", "repeats": args.repeats, "rounds": args.rounds,
              "settings": {k: {"median_ms": round(1000 * statistics.median(v), 2),
                               "mean_kb": round(statistics.mean(sizes[k]) / 1024, 1)} for k, v in times.items()}}
    print(f"{len(samples)} samples of {args.dataset}, {result['channels']} channels at {result['size']}, "
          f"{args.repeats} writes each per setting, {args.rounds} rounds")
    for k, v in result["settings"].items():
        print(f"  {k:<14} {v['median_ms']:7.1f} ms  {v['mean_kb']:7.1f} KB")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
