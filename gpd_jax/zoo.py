"""The shipped models by name: a small registry (as timm's model names or gemma's checkpoint enum).

    gpd_jax.list_models()                    # a ModelCard per shipped model: purpose, tokenizer, data, figures
    gpd_jax.load_model()                     # DEFAULT_MODEL, the best we have on real roads
    gpd_jax.load_model("gpd_maps")           # another by name
    gpd_jax.load_model("runs/mine/export")   # or any exported model or train.py workdir by path

A model is a folder named after it (`config.json`, `params.npz`, a `README.md` that is its card). Folders are found
by name in `$GPD_JAX_MODELS` (a folder holding one sub-folder per model; set it when the package is installed
without its source tree) and then in the `checkpoints/` folder of the source checkout the package runs from. A GPD
names its map tokenizer in its config (`model.map_tokenizer`): a name looked up the same way (after a copy inside
the model's own folder), so a model folder loads wherever it is copied.
"""

from __future__ import annotations

import dataclasses
import os

MODELS_ENV = "GPD_JAX_MODELS"
CONFIG_FILE = "config.json"
_CHECKOUT_MODELS = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "checkpoints")


@dataclasses.dataclass(frozen=True)
class ModelCard:
    """One shipped model: `name` (its folder), `kind` ("gpd" or "map_tokenizer"), a one-line `purpose`, the
    `tokenizer` a GPD reads (a name; None for a tokenizer), the `data` it learned from and their terms, and its
    headline `figures` (on held-out data; the README in its folder has the rest)."""

    name: str
    kind: str
    purpose: str
    tokenizer: str | None
    data: str
    figures: str

    @property
    def path(self) -> str | None:
        """Its folder, or None when no models folder holds it."""
        return find(self.name)


_SUMO_DATA = ("SUMO traffic (eclipse-sumo, EPL-2.0) on generated networks and on real OpenStreetMap road tiles "
              "(ODbL 1.0: (c) OpenStreetMap contributors)")
_RECORDED_DATA = (_SUMO_DATA + "; recorded drone traffic at INTERACTION's five training sites (the INTERACTION "
                  "dataset's terms: non-commercial research only, so these weights are for non-commercial research)")

MODELS: tuple[ModelCard, ...] = (
    ModelCard(
        name="gpd_traffic", kind="gpd",
        purpose="the default: traffic simulation on real roads; its agents step along the scene's vector lanes",
        tokenizer="map_tokenizer", data=_RECORDED_DATA,
        figures="traffic simulation agent ADE / constant velocity at 3 / 5 / 8 s: recorded INTERACTION dev site "
                "0.953 / 0.858 / 0.814, real-road dev tiles 0.770 / 0.741 / 0.734; held-out recorded INTERACTION "
                "sites (test) 0.811 / 0.791 / 0.816, held-out real networks (test) 0.731 / 0.716 / 0.708"),
    ModelCard(
        name="gpd_sampling", kind="gpd",
        purpose="many futures: gpd_traffic plus a sampling agent head, a categorical over 0.5 m cells of each "
                "agent's next position, that rollouts sample (temperature 0.5; at temperature 0 it is gpd_traffic); "
                "RolloutOptions(avoid_collisions=True) decodes its agents among those cells clear of other agents "
                "and of the road edge (a decoding rule, off by default; docs/evaluation.md)",
        tokenizer="map_tokenizer", data=_RECORDED_DATA,
        figures="WOSAC-form realism meta-metric, 32 rollouts, traffic simulation: held-out generated networks "
                "(test) 0.542 against gpd_traffic 0.420, constant velocity 0.312, along the lanes 0.418; held-out "
                "recorded INTERACTION sites 0.618 (0.493, 0.417, 0.500); real-road dev tiles 0.673 (0.567, 0.578, "
                "0.622)"),
    ModelCard(
        name="gpd_maps", kind="gpd",
        purpose="scene generation and map prediction: the best generated maps, on direction-aware map tokens",
        tokenizer="map_tokenizer_directional", data=_SUMO_DATA,
        figures="scene-generation map F1 at 3 s on held-out generated networks 0.34-0.44 (tokenizer ceiling "
                "0.68-0.69); traffic simulation a little behind gpd_traffic on real roads"),
    ModelCard(
        name="gpd_planner", kind="gpd",
        purpose="motion planning: a planning head on the frozen default model that chooses its plan among IDM's "
                "plans along the route at seven target speeds, reading the route, trained in closed loop "
                "(DAgger); the simulator's gpd_head policy",
        tokenizer="map_tokenizer",
        data="the head: SUMO traffic (eclipse-sumo, EPL-2.0) on real OpenStreetMap road tiles (ODbL 1.0: (c) "
             "OpenStreetMap contributors); the backbone is gpd_traffic's, whose recorded INTERACTION traffic makes "
             "these weights non-commercial research only",
        figures="closed loop, plan tracker, NR-CLS / R-CLS-idm / R-CLS-gpd: real-road dev tiles (150) 73.6 / 73.1 / "
                "70.9 (IDM 68.9 / 67.2 / 65.1); held-out recorded INTERACTION sites (108) 63.5 / 62.5 / 63.5 (IDM "
                "55.7 / 50.1 / 58.3); held-out real test networks (99) 71.0 / 70.9 / 69.8 (IDM 71.2 / 68.4 / 69.9); "
                "held-out generated networks (120) 67.9 / 68.7 / 63.3 (IDM 72.7 / 71.2 / 67.9)"),
    ModelCard(
        name="map_tokenizer", kind="map_tokenizer",
        purpose="the map VQ-VAE of gpd_traffic, gpd_sampling and gpd_planner: 256 x 256 binary lane rasters -> 64 "
                "of 128 codes",
        tokenizer=None, data=_SUMO_DATA,
        figures="paper F1 0.60-0.73 on held-out generated networks, 0.13 on SUMO's real networks (cut-free 0.74)"),
    ModelCard(
        name="map_tokenizer_directional", kind="map_tokenizer",
        purpose="the map VQ-VAE of gpd_maps: rasters with lane-heading channels (SLEDGE's occupancy, cos, sin)",
        tokenizer=None, data=_SUMO_DATA,
        figures="paper F1 0.68-0.80 on held-out generated networks, 0.16 on SUMO's real networks (directed "
                "cut-free 0.64)"),
)
DEFAULT_MODEL = "gpd_traffic"


def model_dirs() -> list[str]:
    """Where models are looked up by name, in order: `$GPD_JAX_MODELS` (if set), the checkout's `checkpoints/`
    (if the package runs from a source checkout)."""
    dirs = []
    env = os.environ.get(MODELS_ENV, "").strip()
    if env:
        dirs.append(os.path.abspath(os.path.expanduser(env)))
    if os.path.isdir(_CHECKOUT_MODELS):
        dirs.append(_CHECKOUT_MODELS)
    return dirs


def find(name: str) -> str | None:
    """The folder of the model `name` (a plain folder name) in the first models folder that has it, else None."""
    if not name or os.sep in name or (os.altsep and os.altsep in name) or name in (".", ".."):
        return None
    for d in model_dirs():
        p = os.path.join(d, name)
        if os.path.isfile(os.path.join(p, CONFIG_FILE)):
            return p
    return None


def where_searched() -> str:
    """A phrase naming the models folders searched (for error messages)."""
    dirs = model_dirs()
    env = "" if os.environ.get(MODELS_ENV, "").strip() else f" (${MODELS_ENV} is not set)"
    return (", ".join(dirs) if dirs else "no models folder") + env


def resolve(name_or_path: str | None) -> str:
    """The folder of a model given by name (see `list_models`; None: `DEFAULT_MODEL`) or by path (an exported
    model or a train.py workdir). Raises FileNotFoundError naming what was looked for and where."""
    ref = DEFAULT_MODEL if name_or_path is None else os.fspath(name_or_path)
    if os.path.isfile(os.path.join(ref, CONFIG_FILE)):
        return os.path.abspath(ref)
    found = find(ref)
    if found:
        return found
    if os.path.isdir(ref):
        raise FileNotFoundError(f"{os.path.abspath(ref)}: no {CONFIG_FILE}; expected an exported model or a "
                                "train.py workdir")
    names = ", ".join(c.name for c in MODELS)
    raise FileNotFoundError(f"model {ref!r} not found: not a folder, and not a model in {where_searched()} "
                            f"(shipped: {names})")


def list_models(kind: str | None = None) -> list[ModelCard]:
    """The shipped models (`kind` "gpd" or "map_tokenizer" to filter), the default first."""
    if kind not in (None, "gpd", "map_tokenizer"):
        raise ValueError(f"kind must be 'gpd' or 'map_tokenizer', got {kind!r}")
    return [c for c in MODELS if kind is None or c.kind == kind]


def card(name: str) -> ModelCard:
    """The card of a shipped model (KeyError naming the shipped ones otherwise)."""
    for c in MODELS:
        if c.name == name:
            return c
    raise KeyError(f"no shipped model {name!r}; shipped: {', '.join(c.name for c in MODELS)}")
