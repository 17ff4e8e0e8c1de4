"""File names and small file helpers of the model layer (no heavy imports); the helpers live in
:mod:`lckit.fileio`, shared with recording."""

from lckit.fileio import file_sha256, json_default, read_json, write_json

POLICY_FILE = "policy.safetensors"
"""The file name a training run, a DAgger round or a conversion gives its policy (safetensors + card)."""

__all__ = ["POLICY_FILE", "file_sha256", "json_default", "read_json", "write_json"]
