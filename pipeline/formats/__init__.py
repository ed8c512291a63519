"""Input and output file formats: orientation files, block and scene-point files, DIMAP.

- :mod:`~orthowarp.pipeline.formats.cameras`: interior orientation (:func:`read_cameras`:
  orthority's YAML/JSON, ODM's ``cameras.json``, OpenSfM's ``reconstruction.json``);
- :mod:`~orthowarp.pipeline.formats.exterior`: exterior orientation (:func:`read_exterior`:
  orthority's CSV and GeoJSON, OpenSfM/ODM ``reconstruction.json``);
- :mod:`~orthowarp.pipeline.formats.export`: orthority's formats written (:func:`camera_dict`,
  :func:`export_params`);
- :mod:`~orthowarp.pipeline.formats.block`: block files of the bundle adjustment (JSON) and the
  image and ground point CSV imports;
- :mod:`~orthowarp.pipeline.formats.scene_points`: points measured in pushbroom scenes (JSON, CSV);
- :mod:`~orthowarp.pipeline.formats.dimap`: SPOT level-1A DIMAP metadata, and adjusted scenes
  as JSON;
- :mod:`~orthowarp.pipeline.formats.sensors`: sensor objects from images and orientation files
  (what a batch of orthos, a mosaic or a matching run takes);
- :mod:`~orthowarp.pipeline.formats.rpc`: RPC00B coefficients (image metadata, ``.RPB``,
  ``_RPC.TXT``, orthority's RPC parameter file; :func:`write_rpb`, :func:`write_rpc_txt`) and
  orthority's GCP GeoJSON (:func:`read_gcps`);
- :mod:`~orthowarp.pipeline.formats.exif`: cameras and poses from drone images' EXIF and XMP
  tags (:func:`read_exif`, :func:`exif_orientations`);
- :mod:`~orthowarp.pipeline.formats.gcps`: ground control points of OpenDroneMap's
  ``gcp_list.txt`` (:func:`read_gcp_list`, :func:`match_gcp_images`);
- :mod:`~orthowarp.pipeline.formats.orthos`: orthoimages as sensors from their georeferencing
  (:func:`read_ortho`, :func:`ortho_images`).

Every reader reports a file's unusable content as a one-line
:class:`~orthowarp.errors.ParamError` naming the file, made by one helper
(:func:`~orthowarp.pipeline.formats._parse.fail`, with the package's other shared parsing
helpers). The names below import their module when first used (PEP 562), so that a job loads
only the readers it uses.
"""

_LAZY = {
    "read_cameras": ".cameras",
    "camera_from_entry": ".cameras",
    "MAX_IMAGE_SIZE": ".cameras",
    "NOMINAL_PIXEL_SIZE": ".cameras",
    "ImageOrientation": ".exterior",
    "read_exterior": ".exterior",
    "MAX_COORDINATE": ".exterior",
    "MAX_ANGLE": ".exterior",
    "camera_dict": ".export",
    "export_params": ".export",
    "read_block": ".block",
    "write_block": ".block",
    "block_from_files": ".block",
    "read_image_points_csv": ".block",
    "read_ground_points_csv": ".block",
    "read_scene_points": ".scene_points",
    "write_scene_points": ".scene_points",
    "read_scene_points_csv": ".scene_points",
    "DimapMetadata": ".dimap",
    "read_dimap": ".dimap",
    "read_scene": ".dimap",
    "write_scene": ".dimap",
    "scene_json": ".dimap",
    "write_dimap": ".dimap",
    "FrameOrientation": ".sensors",
    "OdmDataset": ".sensors",
    "image_key": ".sensors",
    "expand_images": ".sensors",
    "image_crs": ".sensors",
    "frame_orientations": ".sensors",
    "frame_sensors": ".sensors",
    "odm_dataset": ".sensors",
    "odm_sensors": ".sensors",
    "RpcFile": ".rpc",
    "GroundControl": ".rpc",
    "read_rpc": ".rpc",
    "read_rpb": ".rpc",
    "read_rpc_txt": ".rpc",
    "read_rpc_param": ".rpc",
    "read_image_rpc": ".rpc",
    "rpc_from_gdal": ".rpc",
    "rpc_to_gdal": ".rpc",
    "write_rpb": ".rpc",
    "write_rpc_txt": ".rpc",
    "read_gcps": ".rpc",
    "rpc_sensor": ".rpc",
    "ExifTags": ".exif",
    "ExifOrientation": ".exif",
    "read_exif": ".exif",
    "exif_camera": ".exif",
    "exif_orientations": ".exif",
    "exif_images": ".exif",
    "gimbal_attitude": ".exif",
    "GcpList": ".gcps",
    "read_gcp_list": ".gcps",
    "match_gcp_images": ".gcps",
    "read_ortho": ".orthos",
    "ortho_images": ".orthos",
}

__all__ = list(_LAZY)


def __getattr__(name: str) -> object:
    import importlib

    if name not in _LAZY:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(_LAZY[name], __name__), name)
    globals()[name] = value  # later look-ups skip this function
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
