"""scikit-learn's parameter protocol without importing scikit-learn (its import costs a CLI
command most of a second): `get_params`/`set_params` over the `__init__` arguments, which an
estimator stores unchanged, so `sklearn.base.clone` works on our models."""
from __future__ import annotations

import inspect


class Params:
    """get_params/set_params/repr for estimators whose parameters are their `__init__` arguments."""

    @classmethod
    def _param_names(cls) -> list[str]:
        sig = inspect.signature(cls.__init__)
        return [p for p in sig.parameters if p != "self"]

    def get_params(self, deep: bool = True) -> dict:
        """The estimator's parameters (its `__init__` arguments).

        Parameters
        ----------
        deep : bool, optional
            Accepted for scikit-learn; there are no nested estimators.

        Returns
        -------
        dict
        """
        return {k: getattr(self, k) for k in self._param_names()}

    def set_params(self, **params):
        """Set parameters by name.

        Parameters
        ----------
        **params
            `__init__` arguments.

        Returns
        -------
        Params
            self.

        Raises
        ------
        ValueError
            For a name that is not an `__init__` argument.
        """
        for k, v in params.items():
            if k not in self._param_names():
                raise ValueError(f"invalid parameter {k!r} for {type(self).__name__}")
            setattr(self, k, v)
        return self

    def __repr__(self) -> str:
        return f"{type(self).__name__}({', '.join(f'{k}={v!r}' for k, v in self.get_params().items())})"
