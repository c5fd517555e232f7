"""A Weights & Biases record of a training run in wandb's offline mode (`esr train --wandb`,
the `wandb` extra): the same scalars as the TensorBoard files (esr_cli/runner/event_log.py), as
`<metric>/seed_<s>` and `<metric>/mean` at step = epoch, with the run's spec as its config.

Nothing leaves the machine: wandb writes `<store>/wandb/<run key>/wandb/offline-run-*/`, and
`wandb sync` on that folder uploads it when the user chooses. The store's runs do not depend on
it: metrics.jsonl is the record. As with the event files, each start or resume of a run writes
the record afresh from the metrics kept, so the folder always holds one offline run with the
whole history, under the run's key as wandb's run id.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from esr_cli.runner.event_log import scalars

WANDB_DIR = "wandb"  # in the store, beside the artifact kinds
PROJECT = "esr"


def wandb_folder(store_root: Path, key: str) -> Path:
    return Path(store_root) / WANDB_DIR / key


class WandbLog:
    """Scalars of metrics rows, logged to an offline wandb run."""

    def __init__(self, folder: Path, key: str, name: str, config: dict, seeds: list[int], rows: list[dict]):
        import wandb  # the optional extra: checked by the CLI before any work

        shutil.rmtree(folder, ignore_errors=True)  # written afresh from the metrics kept
        folder.mkdir(parents=True)
        self.seeds = list(seeds)
        settings = wandb.Settings(silent=True, console="off", disable_git=True, save_code=False,
                                  x_disable_stats=True, x_disable_machine_info=True, x_save_requirements=False)
        self.run = wandb.init(mode="offline", dir=str(folder), project=PROJECT, id=key, name=name, config=config,
                              settings=settings)
        self.append(rows)

    def append(self, rows: list[dict]) -> None:
        for row in rows:
            values = {f"{name}/{run}": value for run, name, value in scalars(row, self.seeds)}
            self.run.log(values, step=int(row["epoch"]))

    def close(self) -> None:
        import wandb

        self.run.finish()
        # finish() can return before wandb's service process has written the run's file (seen:
        # a 7-byte file read right after it); teardown waits for the service, so the record is
        # whole when close returns (the next init starts a service again). A service that died
        # makes teardown call sys.exit: that must not replace the run's own ending (a time limit,
        # a stop, an error) nor skip what follows close; metrics.jsonl is the record either way.
        try:
            wandb.teardown()
        except (Exception, SystemExit):
            pass
