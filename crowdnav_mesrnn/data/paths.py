"""Where the ETH/UCY files are found.

Order (ARCHITECTURE.md): an explicit argument or config value; the ``CROWDNAV_MESRNN_DATA``
environment variable; ``./data/eth_ucy``; ``~/.cache/crowdnav-mesrnn/eth_ucy``.
"""

from __future__ import annotations

import os
from pathlib import Path

ENV_VAR = "CROWDNAV_MESRNN_DATA"

#: How to get the data, appended to every "no data" message (one text, so every message names the command).
HOW_TO_GET_DATA = (
    "The ETH/UCY recordings (SGAN format, metres: all_data/, train/, val/) are not shipped with "
    "crowdnav-mesrnn. Get them with `crowdnav-mesrnn data download` (verified against pinned SHA-256 sums, "
    "installed in ~/.cache/crowdnav-mesrnn/eth_ucy, where the project finds them), or point the project at "
    f"a copy with `export {ENV_VAR}=/path/to/eth_ucy` or `--data-dir`."
)


#: Help text of every ``--data-dir`` option.
DATA_DIR_HELP = f"ETH/UCY folder (default: ${ENV_VAR}, ./data/eth_ucy, ~/.cache/crowdnav-mesrnn/eth_ucy)"
#: Help text of ``--data-dir`` on commands whose environments and workers find the data through ``$ENV_VAR``
#: (:func:`use_data_dir`).
DATA_DIR_ENV_HELP = f"{DATA_DIR_HELP}; sets ${ENV_VAR} for this command and its workers"


class DataNotFoundError(FileNotFoundError):
    """No ETH/UCY data folder was found; the message lists where the project looked."""


def candidate_dirs(data_dir: str | os.PathLike[str] | None = None) -> list[tuple[str, Path]]:
    """The places searched for data, in order, each with a label saying where it came from."""
    out: list[tuple[str, Path]] = []
    if data_dir is not None:
        out.append(("argument", Path(data_dir).expanduser()))
    env = os.environ.get(ENV_VAR)
    if env:
        out.append((f"${ENV_VAR}", Path(env).expanduser()))
    out.append(("working directory", Path.cwd() / "data" / "eth_ucy"))
    out.append(("user cache", Path.home() / ".cache" / "crowdnav-mesrnn" / "eth_ucy"))
    return out


def _looks_like_data(path: Path) -> bool:
    return (path / "all_data").is_dir()


def find_data_dir(data_dir: str | os.PathLike[str] | None = None) -> Path:
    """Return the first data folder holding ``all_data/``.

    An explicit ``data_dir`` that does not hold data is an error even if a later place would
    (a typo should not silently fall through to another copy); the same holds for the
    environment variable.

    Raises:
        DataNotFoundError: with every place looked at and how to provide the data.
    """
    looked: list[str] = []
    for label, path in candidate_dirs(data_dir):
        if _looks_like_data(path):
            return path
        looked.append(f"  {label}: {path} ({'no all_data/ inside' if path.exists() else 'missing'})")
        if label != "working directory" and label != "user cache":
            break
    raise DataNotFoundError("no ETH/UCY data found. Looked in:\n" + "\n".join(looked) + "\n" + HOW_TO_GET_DATA)


def data_available(data_dir: str | os.PathLike[str] | None = None) -> bool:
    """True when :func:`find_data_dir` would succeed."""
    try:
        find_data_dir(data_dir)
    except DataNotFoundError:
        return False
    return True


def use_data_dir(data_dir: str | os.PathLike[str]) -> Path:
    """Check ``data_dir`` holds the data and set ``$CROWDNAV_MESRNN_DATA`` to it for this process and the worker
    processes it starts (commands whose environments and grid cells find the data through the variable).

    Raises:
        DataNotFoundError: ``data_dir`` holds no ``all_data/``.
    """
    path = find_data_dir(data_dir).resolve()
    os.environ[ENV_VAR] = str(path)
    return path
