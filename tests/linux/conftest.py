"""The kernel the tests in this folder run on (:mod:`linux.kernel`): booted once per session (per
xdist worker) on first use, skipped with the reason and the install line where none can run."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from linux.kernel import Kernel, boot, choose


@pytest.fixture(scope="session")
def linux(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Kernel]:
    mode, reason = choose()
    if not mode:
        pytest.skip(reason)
    kernel = boot(mode, tmp_path_factory.mktemp("linux-kernel"))
    yield kernel
    kernel.close()
