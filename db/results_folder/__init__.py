"""The results folder of a job (`docs/results-format.md`): its one writer and its one reader.

- `write`: tiles (16-bit PNG) and their 8-bit display copies, `textured.gml`,
  `orientation.json`, `report.json` and `anomalies.geojson` (`write_results_folder`,
  `write_tile`, `write_json`, `anomalies_document`). `citytherm run`, the database export and the
  service write through it.
- `read`: every textured polygon's texture back on its texel grid, with the grid options the
  job wrote in `report.json` (`iter_surface_textures`).
"""
