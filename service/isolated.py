"""The REST service with its rig in a process of its own: :func:`isolated_service` (what
:func:`service.rig.build_service`, ``lrms serve`` and ``lrms measure`` use).

Start-up order: this module loads nothing beyond the standard library and
:mod:`service.rigproc` (itself standard library only) at load time, so the rig process is
started first and the service's imports (``service.api.core``: SQLAlchemy, the store, the job
runner; about a second) run on a thread while it boots (docs/service.md, "The rig process").
"""

from __future__ import annotations

import contextlib
import threading
from typing import TYPE_CHECKING

from service.supervisor import RigSupervisor

if TYPE_CHECKING:
    from service.api.core import Service
    from service.config import RigConfig


def _import_api() -> None:
    with contextlib.suppress(Exception):  # a failed import is raised again where it is used
        import service.api.core  # noqa: F401  (the Service; the app and its routes only for lrms serve)


def isolated_service(
    config: RigConfig, open_rig: bool = True, *, log_level: str = "warning"
) -> tuple[Service, RigSupervisor]:
    """The REST service for ``config`` with its rig in a process of its own (a
    :class:`RigSupervisor`, opened unless told otherwise): ``(Service, RigSupervisor)``.

    The rig process is started (and waited for) while a thread imports the service, which is
    built once both are done. A rig process that does not start raises
    :class:`service.rigproc.RigProcessError` with its reason.
    """
    sup = RigSupervisor(config, log_level=log_level)
    if open_rig:
        loader = threading.Thread(target=_import_api, name="lrms-import-api", daemon=True)
        loader.start()
        try:
            sup.open()
        finally:
            loader.join()
    from service.api import Service

    svc = Service(config, sup.measure, rig_info=sup.describe, rig_health=sup.health, rig_reset=sup.reset)
    return svc, sup
