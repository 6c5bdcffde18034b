"""Importers, one per source: each reads its source into `RawLog`s and builds a store from them.

* `sumo`: SUMO builds (`build_sumo`): jobs, networks prepared before the runs, windows -> samples; on
  `sumo_networks` (generating and reading road networks, SUMO's real ones, left-hand copies) and `sumo_traffic`
  (demand, parking and drivers, simulation, FCD -> RawLog).
* `nuplan`: nuPlan log databases and maps (`build_nuplan`); `gpkg`: the GeoPackage reader and projections it uses.
* `scenarionet`: scenarios converted by ScenarioNet (Waymo, nuScenes, nuPlan, Argoverse 2, ...; `build_scenarionet`).
* `realnets`: real road-network tiles for training and development (given to `build_sumo` as networks).

Every importer runs its jobs on the shared, source-independent job runner `gpd_jax.data.jobs` (splits by location,
workers, resume, settings check, manifest); `jobs` never imports a source.
"""
