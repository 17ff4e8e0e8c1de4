"""The file helpers of :mod:`lckit.fileio`, under the name lcdata's modules have always imported them by."""

from lckit.fileio import (
    PARTIAL_SUFFIX,
    UnsafePathError,
    check_inside,
    check_output_file,
    check_output_folder,
    check_target,
    file_sha256,
    folder_lock,
    json_default,
    loads_json,
    make_folder,
    open_partial,
    read_json,
    refused_folder,
    remove_file,
    remove_tree,
    write_file,
    write_json,
)

__all__ = ["PARTIAL_SUFFIX", "UnsafePathError", "check_inside", "check_output_file", "check_output_folder",
           "check_target", "file_sha256", "folder_lock", "json_default", "loads_json", "make_folder",
           "open_partial", "read_json", "refused_folder", "remove_file", "remove_tree", "write_file", "write_json"]
