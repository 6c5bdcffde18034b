"""`python -m gpd_jax.checkpoint export|average ...` (the same as `gpd-jax checkpoint`): `main` in the package.

A package with this file, not a module run as a script: the top-level package imports gpd_jax.checkpoint for its
API, and runpy warns when the module it is asked to run is already imported."""

from gpd_jax.checkpoint import main

raise SystemExit(main())
