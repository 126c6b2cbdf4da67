"""Validation against ASAM's XSD schemas, the copies scenariogeneration ships (OpenSCENARIO 1.0-1.3,
OpenDRIVE 1.7), with lxml. Nothing is fetched: the schemas are files of the installed package."""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

from genesis_rl.core.errors import UserInputError

SCENARIO_SCHEMAS = {0: "OpenSCENARIO_1_0.xsd", 1: "OpenSCENARIO_1_1.xsd", 2: "OpenSCENARIO_1_2.xsd",
                    3: "OpenSCENARIO_1_3_1.xsd"}
OPENDRIVE_SCHEMA = "opendrive_17_core.xsd"
INSTALL_HINT = ("the OpenSCENARIO export needs the openscenario extra: pip install -e '.[openscenario]' "
                "(or GENESIS_EXTRAS=openscenario bash scripts/setup.sh)")


def require_scenariogeneration() -> Any:
    try:
        import scenariogeneration
    except ImportError:
        raise UserInputError(INSTALL_HINT) from None
    return scenariogeneration


def schema_folder() -> Path:
    """Where scenariogeneration installed ASAM's schemas (a top-level ``schemas`` folder beside it)."""
    package = Path(require_scenariogeneration().__file__).resolve().parent
    folder = package.parent / "schemas"
    if not (folder / SCENARIO_SCHEMAS[0]).is_file():
        raise UserInputError(f"ASAM's schemas are not in {folder}; reinstall scenariogeneration ({INSTALL_HINT})")
    return folder


@lru_cache(maxsize=8)
def _schema(name: str) -> Any:
    from lxml import etree

    return etree.XMLSchema(etree.parse(str(schema_folder() / name)))


@dataclass(frozen=True)
class Validation:
    """The schema a file was checked against and the errors found (none: valid)."""

    schema: str
    errors: tuple[str, ...]

    @property
    def valid(self) -> bool:
        return not self.errors


def validate(path: Path, schema_name: str) -> Validation:
    from lxml import etree

    schema = _schema(schema_name)
    ok = schema.validate(etree.parse(str(path)))
    errors = () if ok else tuple(f"line {e.line}: {e.message}" for e in schema.error_log)
    return Validation(schema_name, errors)


def scenario_minor_version(path: Path) -> int:
    """The minor version a scenario file declares in its ``FileHeader`` (``revMinor``)."""
    from lxml import etree

    header = etree.parse(str(path)).getroot().find("FileHeader")
    if header is None or header.get("revMajor") != "1" or header.get("revMinor") is None:
        raise UserInputError(f"'{path}' has no OpenSCENARIO 1.x FileHeader (revMajor 1, revMinor)")
    minor = int(header.get("revMinor"))
    if minor not in SCENARIO_SCHEMAS:
        raise UserInputError(f"'{path}': OpenSCENARIO 1.{minor}; allowed: "
                             + ", ".join(f"1.{m}" for m in SCENARIO_SCHEMAS))
    return minor


def validate_scenario(path: Path) -> Validation:
    """A scenario checked against the XSD of the version its header declares."""
    return validate(path, SCENARIO_SCHEMAS[scenario_minor_version(path)])


def validate_opendrive(path: Path) -> Validation:
    return validate(path, OPENDRIVE_SCHEMA)
