"""Path parameters by pattern: a Starlette URL convertor that matches only a resource's own ids, so
that fixed sub-paths (``/recipes/{name}.toml``, ``/calibrations/upload``) are never taken for one."""

from __future__ import annotations

from starlette.convertors import Convertor, register_url_convertor


def register_path_pattern(name: str, pattern: str) -> None:
    """Register ``{param:name}`` for paths: the parameter matches ``pattern`` (a ``^...$`` regex, as
    the pydantic models use it) and is passed on as the string; anything else is a 404."""

    class _Pattern(Convertor[str]):
        regex = pattern.removeprefix("^").removesuffix("$")

        def convert(self, value: str) -> str:
            return value

        def to_string(self, value: str) -> str:
            return value

    register_url_convertor(name, _Pattern())
