"""Training command line for both stages (the same as `gpd-jax train`).

    python train.py --config configs/gpd_tiny.py --workdir runs/tiny [--config.a.b=value ...]
    python train.py --config configs/map_tokenizer.py:tiny --workdir runs/tok [...]

`python train.py --help` lists the config files and the override syntax; gpd_jax/training/command.py has the rest.
"""

import sys

from gpd_jax.training.command import main

if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
