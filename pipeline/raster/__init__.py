"""Raster outputs: files that appear whole or not at all, TIFF structure, the streaming COG writer.

- :mod:`~orthowarp.pipeline.raster.io`: atomic outputs (temporaries, publishing together,
  :func:`~orthowarp.pipeline.raster.io.outputs_together`), :func:`~orthowarp.pipeline.raster.io.write_raster`
  and the other writers, the error helpers that name a failed write's cause;
- :mod:`~orthowarp.pipeline.raster.tiff`: TIFF and BigTIFF headers, IFDs and tags, and
  :func:`~orthowarp.pipeline.raster.tiff.verify_tiff`, the check that a written file holds
  every block;
- :mod:`~orthowarp.pipeline.raster.cog`: :class:`~orthowarp.pipeline.raster.cog.CogWriter`,
  cloud-optimized GeoTIFFs (deflate, zstd, JPEG, WebP or uncompressed) streamed tile by tile,
  and its picklable block work, :class:`~orthowarp.pipeline.raster.cog.TileEncoder`;
- :mod:`~orthowarp.pipeline.raster.device`: the COG's block work (predictor, masks,
  overviews, deflate, zstd or JPEG) on a Warp device;
- :mod:`~orthowarp.pipeline.raster.jpeg`: orthowarp's JPEG encoder on a Warp device.

Nothing here imports the rest of the pipeline; ``io`` and ``cog`` both read TIFFs through
``tiff``, which imports neither. The modules are imported where used (``device`` loads Warp).
"""
