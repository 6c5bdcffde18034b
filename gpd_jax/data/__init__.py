"""Data: sources (SUMO, nuPlan, ScenarioNet) -> RawLog -> fixed-shape samples -> sharded store -> Scene batches.

Modules by job (import what you need; nothing is imported here so that the CLI starts fast):

* `raw`: `RawLog`, what every source produces; `errors`: `DataError`.
* `sources`: one importer per source (reader + build), on the shared job runner `jobs`:
  `sources.sumo` (SUMO builds: jobs, networks prepared before the runs, windows -> samples, `build_sumo`),
  `sources.sumo_networks` (networks: netgenerate, given, SUMO's real ones, left-hand copies; reading lanes and
  areas), `sources.sumo_traffic` (demand, parking, drivers, simulation, FCD -> RawLog), `sources.nuplan` (nuPlan
  log databases and maps -> RawLog, `build_nuplan`; `sources.gpkg`: GeoPackage reading and projections),
  `sources.scenarionet` (ScenarioNet scenario pickles -> RawLog, `build_scenarionet`), `sources.realnets` (real
  road-network tiles for training and development).
* `jobs`: the job runner every importer shares: splits by location, workers, resume, settings check, manifest.
* `netgeom`: lane-geometry fingerprints of networks and the near-duplicate check between splits / stores.
* `preprocess`: RawLog -> samples (scene frame, nearest vehicles, clipped lane polylines); `boxes`: oriented-box
  overlap (the overlap gate); `roadgeom`: drivable areas and road edges of a sample.
* `lanes`: SLEDGE vector lanes of a frame (50 x 20 points) from polylines + ego pose.
* `store`: shard layout, `dataset.json` manifest, `save_map_tokens`; `safe_pickle`: the restricted unpickler.
* `loader`: grain loader of Scene batches (`make_loader`), `load_split`, `benchmark`.
* `inspection`: dataset statistics; `augment`: mirror images of a store; `pack`: a store cut to what a model reads.

Command line: `python -m gpd_jax.data {build,inspect,bench-loader,near-duplicates,mirror,pack,realnets} ...`.
"""
