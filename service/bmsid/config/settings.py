"""The daemon's settings: one pydantic-settings model read from TOML with ``BMSID_...`` overrides.

Precedence, highest first: environment variables (``BMSID_MQTT__URL``, nested with ``__``), then
the TOML file, then the defaults below. Relative paths in the file are resolved against the
file's directory; relative paths from the environment against the working directory.
Secrets are :class:`~pydantic.SecretStr` (printed redacted); the MQTT password may instead come
from ``password_file``, read when the daemon connects.
"""

from __future__ import annotations

import hashlib
import json
import tomllib
from pathlib import Path
from typing import Annotated, Any, Literal, Self
from urllib.parse import urlsplit

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    SecretStr,
    Strict,
    ValidationError,
    field_validator,
    model_validator,
)
from pydantic.functional_validators import AfterValidator
from pydantic_settings import BaseSettings, PydanticBaseSettingsSource, SettingsConfigDict

from bmsid.config.cell import CellConfig, load_cell_config, paper_cell
from bmsid.errors import UserError
from bmsid.estimate.tuning import EstimatorTuning, Variant
from bmsid.gates import GateConfig

MQTT_SCHEMES = {"mqtt": False, "tcp": False, "mqtts": True, "tls": True, "ssl": True}
DEFAULT_PORTS = {False: 1883, True: 8883}


class _Strict(BaseModel):
    # strict: a value of the wrong TOML type (n_cells = "8") is refused, not coerced; an int
    # still fills a float field, and the environment's text is converted by pydantic-settings.
    model_config = ConfigDict(
        extra="forbid", frozen=True, strict=True, use_attribute_docstrings=True
    )


#: A path field: TOML and the environment give text, which strict mode would refuse.
LaxPath = Annotated[Path, Strict(False)]


def _check_topic_prefix(value: str) -> str:
    if not value:
        raise ValueError("must not be empty")
    if "+" in value or "#" in value:
        raise ValueError("must not contain the MQTT wildcards '+' or '#'")
    if any(level == "" for level in value.split("/")):
        raise ValueError("must not have empty levels (leading, trailing or double '/')")
    if "\x00" in value:
        raise ValueError("must not contain NUL")
    if value.startswith("$"):
        raise ValueError("must not start with '$' (topics reserved for the broker, e.g. $SYS)")
    return value


TopicPrefix = Annotated[str, AfterValidator(_check_topic_prefix)]


class ReplaySettings(_Strict):
    """Replay a candump log onto the ``virtual`` bus from inside the daemon (demo, tests)."""

    log: LaxPath

    """candump log (``candump -l`` or console format) to replay."""
    speed: float = Field(20.0, gt=0.0, le=100_000.0)
    """Replay rate as a multiple of real time (log timestamps are kept on the frames)."""
    start_delay_s: float = Field(0.5, ge=0.0)
    """Wait this long after the bus opens before the first frame, s."""
    channel: str | None = Field(None, min_length=1)
    """The log's CAN interface (``can1``) whose frames are replayed; None = the log must carry
    the mapping's frames on one interface only (two packs mixed would give garbage)."""


class CanSettings(_Strict):
    """Input bus, decoding, and the parameter frames bmsid sends back."""

    interface: Literal["socketcan", "virtual"] = "socketcan"

    """python-can interface: ``socketcan`` on a gateway, ``virtual`` (in-process) for demos."""
    channel: str = Field("can0", min_length=1)
    """Network interface (``can0``, ``vcan0``) or virtual channel name."""
    mapping: LaxPath | None = None
    """Bus mapping TOML (which signals carry current and voltages); None = bmsid's own DBC."""
    n_cells: int = Field(ge=1, le=512)
    """Cells in series identified (the first n of the mapping)."""
    staleness_s: float = Field(2.0, gt=0.0)
    """A half-complete cycle or a current older than this is closed/dropped (frames_to_samples)."""
    reader_queue_frames: int = Field(20_000, ge=100)
    """Frames buffered between socket and decoder; beyond that, frames are dropped and counted."""
    output: bool = True
    """Send the parameter frames on the bus."""
    output_dbc: LaxPath | None = None
    """DBC of the parameter frames; None = bmsid's own ``bmsid.dbc``."""
    output_period_s: float = Field(0.1, gt=0.0)
    """One round of parameter frames (pack summary + the next cells) every this many s."""
    output_extended_id: bool = True
    """29-bit ids for the parameter frames (False: the 11-bit twins)."""
    output_fd: bool = False
    """Send one 48-byte CAN FD frame per cell instead of three classic frames."""
    bitrate_bps: int = Field(500_000, gt=0)
    """Bus bit rate, bit/s: the base of ``max_bus_share``."""
    max_bus_share: float = Field(0.05, gt=0.0, le=0.5)
    """The parameter frames never use more than this share of the bus bit rate."""
    reopen_min_s: float = Field(0.5, gt=0.0)
    """First delay before reopening a failed or missing interface, s (doubled each time)."""
    reopen_max_s: float = Field(30.0, gt=0.0)
    """Longest delay between two reopen attempts, s."""
    replay: ReplaySettings | None = None
    """Replay a candump log onto the virtual bus (demo, tests)."""

    @model_validator(mode="after")
    def _check(self) -> Self:
        if self.replay is not None and self.interface != "virtual":
            raise ValueError("replay needs interface = 'virtual'")
        if self.reopen_min_s > self.reopen_max_s:
            raise ValueError("reopen_min_s must be <= reopen_max_s")
        return self


class EstimatorSettings(_Strict):
    """Cell type, estimator variant and tuning."""

    cell: LaxPath | None = None
    """Cell config TOML/JSON (``bmsid fit-ocv``); None = the paper's 70 Ah NMC cell."""
    variant: Variant = "hy-affrls-lpso"
    """``hy-affrls-lpso`` (the paper's fusion), ``hy-affrls`` or ``non-hy-affrls`` (baselines)."""
    tuning: EstimatorTuning = EstimatorTuning()
    """Estimator constants (defaults are the documented physics-based choices)."""
    soc0: float | None = Field(None, ge=0.0, le=1.0)
    """Initial SOC (fraction) for a fresh start; None applies the cell's ``soc_init`` policy."""
    isolation: Literal["process", "thread"] = "process"
    """Run the bank in a child process (the event loop keeps its 5 ms budget under load) or in
    a thread of the daemon (platforms that cannot spawn processes)."""
    kernels: Literal["compiled", "numpy"] = "compiled"
    """The estimator's per-tick kernels and swarm window fits compiled by numba (where it
    compiles; else numpy) or run on their numpy reference (``estimate/jit.py``): results equal
    to rounding, decisions alike. ``numpy`` where a sandbox forbids writable executable memory
    (systemd's MemoryDenyWriteExecute, as the shipped unit sets)."""

    def load_cell(self) -> CellConfig:
        if self.cell is None:
            return paper_cell()
        try:
            return load_cell_config(self.cell)
        except FileNotFoundError:
            raise UserError(f"estimator.cell: file not found: {self.cell}") from None
        except ValidationError as exc:
            raise UserError(f"estimator.cell: {self.cell}: {_first_error(exc)}") from None
        except (OSError, ValueError) as exc:
            raise UserError(f"estimator.cell: cannot read {self.cell}: {exc}") from None


class HomeAssistantSettings(_Strict):
    """Home Assistant MQTT discovery (retained config messages, re-sent when HA comes online)."""

    enabled: bool = False
    """Publish discovery config for every cell and pack sensor."""
    prefix: TopicPrefix = "homeassistant"
    """Home Assistant's discovery prefix; same rules as ``topic_prefix``."""


def parse_mqtt_url(url: str) -> tuple[str, int, bool]:
    """(host, port, tls) of an ``mqtt://``/``mqtts://`` URL; ValueError saying what to write."""
    parts = urlsplit(url)
    if "://" not in url:
        raise ValueError(f"{url!r} has no scheme: write mqtt://HOST[:PORT] (mqtts:// for TLS)")
    if parts.scheme not in MQTT_SCHEMES:
        raise ValueError(
            f"url scheme must be one of {', '.join(MQTT_SCHEMES)}, got {parts.scheme!r}"
        )
    if not parts.hostname:
        raise ValueError(f"url {url!r} has no host")
    if parts.path not in ("", "/") or parts.query or parts.username or parts.password:
        raise ValueError("url takes scheme://host[:port] only (credentials go in username/...)")
    tls = MQTT_SCHEMES[parts.scheme]
    try:
        port = parts.port or DEFAULT_PORTS[tls]
    except ValueError as exc:
        raise ValueError(f"url port: {exc}") from None
    return parts.hostname, port, tls


class MqttSettings(_Strict):
    """Broker connection, credentials, TLS and topics (``<topic_prefix>/<pack_id>/...``)."""

    enabled: bool = True
    """Publish on MQTT at all (False: CAN output only)."""
    url: str = "mqtt://localhost:1883"
    """``mqtt://host[:port]`` (also ``tcp://``) or ``mqtts://host[:port]`` (also ``tls://``)."""
    username: str | None = None
    """Broker user name; None connects anonymously (then no password may be set)."""
    password: SecretStr | None = None
    """Broker password, never printed; better ``password_file`` or env ``BMSID_MQTT__PASSWORD``."""
    password_file: LaxPath | None = None
    """File holding the password (trailing newline stripped), read at every connect attempt."""
    ca_file: LaxPath | None = None
    """PEM CA certificate(s) the broker's certificate must chain to; None = system trust store."""
    cert_file: LaxPath | None = None
    """PEM client certificate for brokers that require one (``mqtts://``); needs ``key_file``."""
    key_file: LaxPath | None = None
    """Unencrypted PEM private key of ``cert_file`` (may be the same file); keep it mode 600."""
    tls_insecure: bool = False
    """Tests only: skip the broker certificate and host name checks (logged as a warning)."""
    client_id: str | None = None
    """Unique per daemon (two clients with one id kick each other off); default bmsid-<pack_id>."""
    qos: int = Field(1, ge=0, le=2)
    """QoS of the cell and pack messages (status and discovery always use 1)."""
    topic_prefix: TopicPrefix = "bmsid"
    """First topic level(s); no wildcards ``+``/``#``, no empty levels, no leading ``$``."""
    publish_period_s: float = Field(1.0, ge=0.0)
    """Least sample time between two publications of the cells, s (0: every estimator tick)."""
    outbox_size: int = Field(100_000, ge=10)
    """Messages held while the broker is away; when full the oldest are dropped and counted."""
    keepalive_s: int = Field(30, ge=5)
    """MQTT keep-alive interval, s (the broker drops the client after 1.5x without traffic)."""
    reconnect_min_s: float = Field(0.5, gt=0.0)
    """First reconnect delay, s; doubled (with +-20 % jitter) after each failure."""
    reconnect_max_s: float = Field(30.0, gt=0.0)
    """Longest reconnect delay, s; login and TLS failures go straight to it after one retry."""
    publish_timeout_s: float = Field(10.0, gt=0.0)
    """Longest wait for the broker's CONNACK or publish acknowledgement, s."""
    max_inflight: int = Field(20, ge=1, le=1000)
    """Unacknowledged QoS 1/2 messages the client allows at once."""
    homeassistant: HomeAssistantSettings = HomeAssistantSettings()
    """Home Assistant MQTT discovery."""

    @model_validator(mode="after")
    def _check(self) -> Self:
        _, _, tls = self.endpoint()  # raises ValueError on a bad URL
        if self.password is not None and self.password_file is not None:
            raise ValueError("set password or password_file, not both")
        if self.username is None and (self.password is not None or self.password_file is not None):
            raise ValueError("a password (password or password_file) needs a username")
        if (self.cert_file is None) != (self.key_file is None):
            raise ValueError("a client certificate needs both cert_file and key_file")
        if not tls:
            tls_only = [
                name
                for name in ("ca_file", "cert_file", "key_file", "tls_insecure")
                if getattr(self, name) not in (None, False)
            ]
            if tls_only:
                raise ValueError(
                    f"{', '.join(tls_only)} need(s) a TLS url (mqtts://), got {self.url!r}"
                )
        if self.reconnect_min_s > self.reconnect_max_s:
            raise ValueError("reconnect_min_s must be <= reconnect_max_s")
        return self

    @field_validator("url")
    @classmethod
    def _check_url(cls, url: str) -> str:
        parse_mqtt_url(url)  # its errors name mqtt.url, not the whole section
        return url

    def endpoint(self) -> tuple[str, int, bool]:
        """(host, port, tls) of ``url``."""
        return parse_mqtt_url(self.url)

    def password_value(self) -> str | None:
        """The password, read from ``password_file`` when set (trailing newline stripped).

        Raises:
            UserError: naming ``mqtt.password_file`` when it is missing, unreadable or empty
                (never with its content).
        """
        if self.password_file is not None:
            try:
                raw = self.password_file.read_bytes()
            except OSError as exc:
                raise UserError(
                    f"mqtt.password_file: cannot read {self.password_file}: "
                    f"{exc.strerror or type(exc).__name__}"
                ) from None
            try:
                value = raw.decode("utf-8").rstrip("\r\n")
            except UnicodeDecodeError:
                raise UserError(
                    f"mqtt.password_file: {self.password_file} is not UTF-8 text"
                ) from None
            if not value:
                raise UserError(f"mqtt.password_file: {self.password_file} is empty")
            return value
        return self.password.get_secret_value() if self.password is not None else None


class StateSettings(_Strict):
    """Where the estimator state survives restarts."""

    directory: LaxPath = Path("/var/lib/bmsid")
    """Checkpoints (``<pack_id>.ckpt.npz``) and the sequence file (``<pack_id>.seq``)."""
    checkpoint_period_s: float = Field(60.0, gt=0.0)
    """Atomic checkpoint of the whole estimator state every this many s (and at shutdown)."""
    restore: bool = True
    """Restore the checkpoint at start when pack id, cell count and config match."""


class Settings(BaseSettings):
    """Everything ``bmsid run`` needs (see ``configs/bmsid.example.toml``)."""

    model_config = SettingsConfigDict(
        env_prefix="BMSID_",
        env_nested_delimiter="__",
        extra="forbid",
        frozen=True,
        strict=True,  # as _Strict; pydantic-settings then converts the environment's text
        nested_model_default_partial_update=True,
        use_attribute_docstrings=True,
    )

    pack_id: str = Field(pattern=r"^[A-Za-z0-9_.-]{1,64}$")

    """Names the pack in topics and checkpoints: letters, digits, ``_.-``."""
    # strict=False on the sections lets them be given as dicts in code (the mypy plugin types a
    # strict field by its model); each section's own fields stay strict.
    can: CanSettings = Field(strict=False)
    estimator: EstimatorSettings = Field(EstimatorSettings(), strict=False)
    mqtt: MqttSettings = Field(MqttSettings(), strict=False)
    state: StateSettings = Field(StateSettings(), strict=False)
    gates: GateConfig = Field(GateConfig(), strict=False)
    """Plausibility gates before the estimators: a refused reading is a missing channel for
    its tick, counted per cell in the status (limits from the cell config by default)."""
    status_period_s: float = Field(10.0, gt=0.0)
    """Counters go to the status topic this often, s."""
    log_period_s: float = Field(300.0, gt=0.0)
    """A counters line goes to the log (INFO) this often, s: the journal shows a healthy
    daemon without filling up."""
    systemd_notify: bool = True
    """Send READY/WATCHDOG/STOPPING to $NOTIFY_SOCKET when systemd set one."""

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        # The environment overrides the file (passed as init arguments by load_settings).
        return env_settings, init_settings

    def client_id(self) -> str:
        return self.mqtt.client_id or f"bmsid-{self.pack_id}"

    def config_hash(self, cell: CellConfig) -> str:
        """Hash of what a checkpoint's estimator state depends on (not I/O settings)."""
        key = {
            "pack_id": self.pack_id,
            "n_cells": self.can.n_cells,
            "variant": self.estimator.variant,
            "tuning": self.estimator.tuning.model_dump(mode="json"),
            "cell": cell.model_dump(mode="json"),
        }
        return hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:16]

    def config_parts(self, cell: CellConfig) -> dict[str, str]:
        """The estimator parts ``config_hash`` covers, each as text a checkpoint header keeps
        to name what changed (the variant as it is, tuning and cell config as hashes)."""

        def digest(data: Any) -> str:
            return hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()[:12]

        return {
            "variant": self.estimator.variant,
            "tuning": digest(self.estimator.tuning.model_dump(mode="json")),
            "cell": f"{cell.name} {digest(cell.model_dump(mode='json'))}",
        }

    def redacted(self) -> dict[str, Any]:
        """The effective settings as plain data, secrets shown as ``**********``."""
        data: dict[str, Any] = self.model_dump(mode="json", exclude_none=True)
        return data


#: Keys holding paths, resolved relative to the config file.
_PATH_KEYS = (
    ("can", "mapping"),
    ("can", "output_dbc"),
    ("can", "replay", "log"),
    ("estimator", "cell"),
    ("mqtt", "password_file"),
    ("mqtt", "ca_file"),
    ("mqtt", "cert_file"),
    ("mqtt", "key_file"),
    ("state", "directory"),
)


def _resolve_paths(data: dict[str, Any], base: Path) -> None:
    for keys in _PATH_KEYS:
        node: Any = data
        for k in keys[:-1]:
            node = node.get(k) if isinstance(node, dict) else None
        if isinstance(node, dict) and isinstance(node.get(keys[-1]), str):
            p = Path(node[keys[-1]]).expanduser()
            node[keys[-1]] = str(p if p.is_absolute() else (base / p).resolve())


def _first_error(exc: ValidationError) -> str:
    errors = exc.errors()
    err = errors[0]
    field = ".".join(str(p) for p in err["loc"]) or "(top level)"
    more = f" (and {len(errors) - 1} more)" if len(errors) > 1 else ""
    value = ""
    if err["type"] not in ("missing", "extra_forbidden") and "input" in err:
        shown = err["input"]
        if "password" not in field and not isinstance(shown, dict | list):
            value = f" (got {shown!r})"
        if isinstance(shown, str) and err["type"] in ("int_type", "float_type", "bool_type"):
            value = f" (got the string {shown!r}: write it without quotes)"
    msg = "unknown field" if err["type"] == "extra_forbidden" else err["msg"]
    return f"field {field}: {msg}{value}{more}"


def load_settings(path: str | Path) -> Settings:
    """Read and validate a settings TOML (+ environment); UserError with the field on failure."""
    p = Path(path)
    try:
        data = tomllib.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise UserError(f"config file not found: {p}") from None
    except OSError as exc:
        raise UserError(f"cannot read config {p}: {exc.strerror}") from None
    except (UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise UserError(f"{p}: not valid TOML: {exc}") from None
    _resolve_paths(data, p.resolve().parent)
    try:
        return Settings(**data)
    except ValidationError as exc:
        raise UserError(f"{p}: {_first_error(exc)}") from None
