"""Protobuf messages of lc-toolkit (package ``lc``).

``lc.proto`` is the source; ``lc_pb2.py`` is generated from it by ``python tools/gen_protos.py``
(grpcio-tools) and committed. Never edit ``lc_pb2.py`` by hand.
"""
