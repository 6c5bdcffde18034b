"""Data: sources (SUMO, nuPlan) -> RawLog -> fixed-shape samples -> sharded store -> Scene batches.

Modules (import what you need; nothing is imported here so that the CLI starts fast):

* `raw`: `RawLog`, what every source produces; `errors`: `DataError`.
* `sumo`: networks (netgenerate, given, or SUMO's real ones), demand, simulation, FCD -> RawLog.
* `netgeom`: lane-geometry fingerprints of networks and the near-duplicate check between splits / stores.
* `nuplan`: nuPlan log databases and maps -> RawLog.
* `preprocess`: RawLog -> samples (scene frame, nearest vehicles, clipped lane polylines).
* `lanes`: SLEDGE vector lanes of a frame (50 x 20 points) from polylines + ego pose.
* `store`: shard layout, `dataset.json` manifest, `save_map_tokens`.
* `loader`: grain loader of Scene batches (`make_loader`), `load_split`, `benchmark`.
* `build`: builds with workers, resume and splits by location; `inspection`: dataset statistics.

Command line: `python -m gpd_jax.data {build,inspect,bench-loader,near-duplicates} ...`.
"""
