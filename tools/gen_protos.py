"""Regenerate ``lcdata/proto/*_pb2.py`` from the ``.proto`` sources with grpcio-tools.

Usage (from a checkout, with the dev extras installed)::

    python tools/gen_protos.py

The generated modules are committed, so users never need grpcio-tools; run this after editing
``lcdata/proto/lc.proto`` and commit both files.
"""

from __future__ import annotations

import argparse
import logging
import pathlib
import sys

ROOT = pathlib.Path(__file__).resolve().parents[1]
PROTO_DIR = ROOT / "lcdata" / "proto"

log = logging.getLogger("gen_protos")


def main(argv: list[str] | None = None) -> int:
    """Compile every ``.proto`` in ``lcdata/proto`` to a ``*_pb2.py`` next to it."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--proto-dir", type=pathlib.Path, default=PROTO_DIR)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        from grpc_tools import protoc
    except ImportError:
        log.error("grpcio-tools is missing: pip install grpcio-tools")
        return 1
    protos = sorted(args.proto_dir.glob("*.proto"))
    if not protos:
        log.error("no .proto files in %s", args.proto_dir)
        return 1
    for proto in protos:
        cmd = ["protoc", f"-I{args.proto_dir}", f"--python_out={args.proto_dir}", str(proto)]
        if protoc.main(cmd) != 0:
            log.error("protoc failed on %s", proto)
            return 1
        log.info("generated %s", proto.with_name(proto.stem + "_pb2.py").relative_to(ROOT))
    return 0


if __name__ == "__main__":
    sys.exit(main())
