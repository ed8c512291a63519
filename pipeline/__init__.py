"""Host orchestration: DEM preparation, kernel launches, tiling and file I/O."""
