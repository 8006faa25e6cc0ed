"""A progress bar over the forward folds (:mod:`models.fit.forward`), from outside them.

:func:`models.fit.forward.forward_validate` fits one model per predicted unit through the
factory it is given; counting the factory's calls shows how far it is without a bar in
the validation itself. The bar reads "k/N" while the k-th fold's model is fitted.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager

from tqdm import tqdm

from models.base import ThermalModel
from models.data.features import Prepared
from models.fit.forward import first_predicted, forward_units


def forward_fold_count(prepared: Prepared) -> int:
    """How many models :func:`models.fit.forward.forward_validate` fits on ``prepared``."""
    _, units = forward_units(prepared)
    start = first_predicted(units)
    return 0 if start is None else len(units) - start


@contextmanager
def counted(
    factory: Callable[[], ThermalModel], prepared: Prepared, progress: bool
) -> Iterator[Callable[[], ThermalModel]]:
    """``factory``, advancing a "forward folds" bar (stderr) at each model it makes."""
    bar = tqdm(total=forward_fold_count(prepared), desc="forward folds", unit="fold",
               disable=not progress, leave=False, mininterval=0)  # fmt: skip

    def made() -> ThermalModel:
        bar.update(1)
        return factory()

    with bar:
        yield made
