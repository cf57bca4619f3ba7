"""The `tissuefit` command: `simulate`, `render`, `check`, `compare`, `synthesize`, `fit`, `--version`.

Thin by design: parse the arguments (`_main`), then the chosen subcommand's module (one per
subcommand, imported only when chosen) validates them, calls the library (`tissuefit.trace`,
`trace_spectral`, `tissuefit.render.render`, `tissuefit.fit.fit`, `tissuefit.io`) and writes
through `tissuefit.io`. Invalid input exits with status 2 and a one-line message on stderr, never a
traceback.
"""

from ._main import DEFAULT_SEED as DEFAULT_SEED, EXIT_INVALID as EXIT_INVALID, main as main
