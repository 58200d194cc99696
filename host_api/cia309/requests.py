"""The 309-3 requests as the parser gives them to the server: one frozen dataclass per
command, with the sequence number and the network and node the line named (None: the
line left it to the client's defaults, which are the service layer's business).

Arguments are typed with the model's types (``DataType``, ``PdoMapping``) and CiA 305's
``dpm.cia305.LssAddress``, so the server passes them to the 309-1 services unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass

from dpm.cia305 import LssAddress
from host_api.cia309.model import Cia309Error, DataType, ErrorCode, PdoMapping

NO_LSS_ADDRESS = LssAddress(0, 0, 0, 0)
"""The default of ``_lss_fastscan``'s known numbers and masks: nothing known."""

class ParseError(Cia309Error):
    """A request line the gateway cannot accept; the answer is ``ERROR:<error>``.

    ``sequence`` is the request's sequence number when the line got that far, else None
    (CANopenNode then repeats the previous one, which is 0 on a fresh connection).
    """

    error: ErrorCode

    def __init__(self, error: ErrorCode, sequence: int | None, message: str) -> None:
        super().__init__(error, message)
        self.sequence = sequence


@dataclass(frozen=True, kw_only=True)
class Request:
    """What every request has: the sequence number its answer must echo."""

    sequence: int


@dataclass(frozen=True, kw_only=True)
class NetworkRequest(Request):
    """A request to one network; ``net`` None means the default network."""

    net: int | None = None


@dataclass(frozen=True, kw_only=True)
class NodeRequest(NetworkRequest):
    """A request to one node; ``node`` None means the default node, 0 all nodes (NMT only)."""

    node: int | None = None


@dataclass(frozen=True, kw_only=True)
class SdoUpload(NodeRequest):
    """``r[ead] <index> <subindex> [<datatype>]``; no type means ``hex`` (CANopenNode)."""

    index: int
    subindex: int
    dtype: DataType | None = None


@dataclass(frozen=True, kw_only=True)
class SdoDownload(NodeRequest):
    """``w[rite] <index> <subindex> <datatype> <value>``, the value already in CiA 301 bytes."""

    index: int
    subindex: int
    dtype: DataType
    data: bytes


@dataclass(frozen=True, kw_only=True)
class StartNode(NodeRequest):
    """``start``: NMT start remote node."""


@dataclass(frozen=True, kw_only=True)
class StopNode(NodeRequest):
    """``stop``: NMT stop remote node."""


@dataclass(frozen=True, kw_only=True)
class EnterPreoperational(NodeRequest):
    """``preop[erational]``: NMT enter pre-operational."""


@dataclass(frozen=True, kw_only=True)
class ResetNode(NodeRequest):
    """``reset node``: NMT reset node (application)."""


@dataclass(frozen=True, kw_only=True)
class ResetCommunication(NodeRequest):
    """``reset comm[unication]``: NMT reset communication."""


@dataclass(frozen=True, kw_only=True)
class EnableGuarding(NodeRequest):
    """``enable guarding <guard time ms> <life time factor>``."""

    guard_time: int
    lifetime_factor: int


@dataclass(frozen=True, kw_only=True)
class DisableGuarding(NodeRequest):
    """``disable guarding``."""


@dataclass(frozen=True, kw_only=True)
class EnableHeartbeat(NodeRequest):
    """``enable heartbeat <consumer time ms>``: start the heartbeat consumer for the node."""

    consumer_time: int


@dataclass(frozen=True, kw_only=True)
class DisableHeartbeat(NodeRequest):
    """``disable heartbeat``: stop consuming the node's heartbeat."""


@dataclass(frozen=True, kw_only=True)
class SetSdoTimeout(NetworkRequest):
    """``set sdo_timeout <ms>``: the time-out of all client SDOs."""

    timeout_ms: int


@dataclass(frozen=True, kw_only=True)
class SetSdoBlock(NetworkRequest):
    """``set sdo_block <0|1>`` (CANopenNode): allow SDO block transfer."""

    enabled: bool



@dataclass(frozen=True, kw_only=True)
class ConfigureRpdo(NetworkRequest):
    """``set rpdo <nr> <COB-ID> <tx-type> <n> <mapping>...``; tx-type is ``event``, ``rtr``
    or ``sync<0..240>`` and is kept as its CiA 301 number (0xFF, 0xFD, 0..240)."""

    number: int
    cob_id: int
    transmission_type: int
    mappings: tuple[PdoMapping, ...]


@dataclass(frozen=True, kw_only=True)
class ConfigureTpdo(NetworkRequest):
    """``set tpdo`` as ``set rpdo``; ``set tpdox`` adds, as Lely spells it,
    ``event<inhibit ms> <event timer ms>``, ``rtr <event timer ms>`` or
    ``sync<n> <SYNC start value>``."""

    number: int
    cob_id: int
    transmission_type: int
    mappings: tuple[PdoMapping, ...]
    inhibit_time: int | None = None
    event_timer: int | None = None
    sync_start: int | None = None


@dataclass(frozen=True, kw_only=True)
class ReadPdo(NetworkRequest):
    """``r[ead] p[do] <nr>``: the last data of an RPDO (RTR for types 252/253)."""

    number: int


@dataclass(frozen=True, kw_only=True)
class WritePdo(NetworkRequest):
    """``w[rite] p[do] <nr> <n> <value>...``: the mapped objects' raw values, then send."""

    number: int
    values: tuple[int, ...]


@dataclass(frozen=True, kw_only=True)
class InitGateway(NetworkRequest):
    """``init <bit rate index 0..9>`` (the CiA 305 table, 9 = automatic detection)."""

    bit_rate_index: int


@dataclass(frozen=True, kw_only=True)
class StoreConfiguration(NetworkRequest):
    """``store [<specifier>]``: our spelling; neither open gateway implements 309-1 4.5.3."""

    specifier: int | None = None


@dataclass(frozen=True, kw_only=True)
class RestoreConfiguration(NetworkRequest):
    """``restore [<specifier>]``: our spelling; neither open gateway implements 309-1 4.5.4."""

    specifier: int | None = None


@dataclass(frozen=True, kw_only=True)
class SetHeartbeatProducer(NetworkRequest):
    """``set heartbeat <ms>``: the gateway's own heartbeat producer time (Lely)."""

    producer_time: int


@dataclass(frozen=True, kw_only=True)
class SetNodeId(NetworkRequest):
    """``set id <node-ID>``: the gateway's own node-ID on the network (Lely)."""

    node_id: int


@dataclass(frozen=True, kw_only=True)
class SetBootUpForwarding(NetworkRequest):
    """``boot_up_indication Enable|Disable`` (Lely): forward boot-up events or not."""

    enabled: bool


@dataclass(frozen=True, kw_only=True)
class SetDefaultNode(NetworkRequest):
    """``set node <node-ID>``."""

    node_id: int


@dataclass(frozen=True, kw_only=True)
class GetVersion(NetworkRequest):
    """``info version``."""


@dataclass(frozen=True, kw_only=True)
class SetDefaultNetwork(Request):
    """``set network <net>``."""

    network: int


@dataclass(frozen=True, kw_only=True)
class SetCommandTimeout(Request):
    """``set command_timeout <ms>``."""

    timeout_ms: int


@dataclass(frozen=True, kw_only=True)
class SetCommandSize(Request):
    """``set command_size <bytes>``: the longest request the client will send."""

    size: int


@dataclass(frozen=True, kw_only=True)
class Help(Request):
    """``help [datatype|lss]`` (CANopenNode)."""

    topic: str | None = None


@dataclass(frozen=True, kw_only=True)
class Log(Request):
    """``log`` (CANopenNode): print the message log, where CANopenNode's events go."""


@dataclass(frozen=True)
class LssAddressRange:
    """An LSS address with ranges for revision and serial (309-1 4.8.10 LSS_address_sel)."""

    vendor_id: int
    product_code: int
    revision_low: int
    revision_high: int
    serial_low: int
    serial_high: int


@dataclass(frozen=True)
class LssScanCriterion:
    """One LSS number in ``lss_allnodes``: scan 0 = fastscan it, 1 = ignore, 2 = match value."""

    scan: int
    value: int


@dataclass(frozen=True, kw_only=True)
class LssSwitchGlobal(NetworkRequest):
    """``lss_switch_glob <0|1>``: all slaves to waiting (0) or configuration (1) state."""

    configuration: bool


@dataclass(frozen=True, kw_only=True)
class LssSwitchSelective(NetworkRequest):
    """``lss_switch_sel <vendorID> <product code> <revisionNo> <serialNo>``."""

    address: LssAddress


@dataclass(frozen=True, kw_only=True)
class LssConfigureNodeId(NetworkRequest):
    """``lss_set_node <node-ID>`` (255 makes the slave unconfigured)."""

    node_id: int


@dataclass(frozen=True, kw_only=True)
class LssConfigureBitRate(NetworkRequest):
    """``lss_conf_bitrate <table_selector> <table_index>``."""

    table_selector: int
    table_index: int


@dataclass(frozen=True, kw_only=True)
class LssActivateBitRate(NetworkRequest):
    """``lss_activate_bitrate <switch_delay ms>``."""

    switch_delay_ms: int


@dataclass(frozen=True, kw_only=True)
class LssStore(NetworkRequest):
    """``lss_store``."""


@dataclass(frozen=True, kw_only=True)
class LssInquireAddress(NetworkRequest):
    """``lss_inquire_addr [<n>]``: LSS number 0..3 (vendor, product, revision, serial).

    CANopenNode writes 0..3 and without an argument asks for all four; Lely writes the
    CiA 305 command specifier 0x5A..0x5D, which is mapped here to 0..3.
    """

    lss_sub: int | None = None


@dataclass(frozen=True, kw_only=True)
class LssInquireNodeId(NetworkRequest):
    """``lss_get_node``."""


@dataclass(frozen=True, kw_only=True)
class LssIdentifyRemoteSlave(NetworkRequest):
    """``lss_identity <vendorID> <product> <rev low> <rev high> <serial low> <serial high>``."""

    selection: LssAddressRange


@dataclass(frozen=True, kw_only=True)
class LssIdentifyNonConfigured(NetworkRequest):
    """``lss_ident_nonconf``."""


@dataclass(frozen=True, kw_only=True)
class LssFastscan(NetworkRequest):
    """``lss_fastscan <IDNumber> <BitChecked> <LSSSub> <LSSNext>``: one CiA 305 fastscan
    frame, 309-1 4.8.12; the spelling is ours, by analogy with the other ``lss_`` commands."""

    id_number: int
    bit_checked: int
    lss_sub: int
    lss_next: int


@dataclass(frozen=True, kw_only=True)
class LssIdentifyFastscan(NetworkRequest):
    """``_lss_fastscan``: find one unconfigured slave and select it, both dialects' extension.

    CANopenNode writes ``_lss_fastscan [<timeout ms>]`` (all bits unknown); Lely writes the
    known bits and their masks, ``<vendorID> <mask> <product> <mask> <rev> <mask> <serial>
    <mask>``.
    """

    timeout_ms: int | None = None
    known: LssAddress = NO_LSS_ADDRESS
    mask: LssAddress = NO_LSS_ADDRESS


@dataclass(frozen=True, kw_only=True)
class LssSlowscan(NetworkRequest):
    """``_lss_slowscan`` (Lely): binary search with ``lss_identity``, then select the slave."""

    selection: LssAddressRange


@dataclass(frozen=True, kw_only=True)
class LssAssignNodeId(NetworkRequest):
    """``lss_assign <vendorID> <product> <revisionNo> <serialNo> <node-ID>``: 309-1 4.8.13;
    the spelling is ours (neither open gateway implements it)."""

    address: LssAddress
    node_id: int


@dataclass(frozen=True, kw_only=True)
class LssCompleteConfiguration(NetworkRequest):
    """``lss_allnodes [<timeout ms> [<first node-ID> <store 0|1> [<scan> <value>]*4]]``.

    309-1 4.8.14 without arguments; CANopenNode's optional arguments narrow the scan.
    None means the gateway's default (CANopenNode: 100 ms, node-ID 2, store, scan all).
    """

    timeout_ms: int | None = None
    first_node_id: int | None = None
    store: bool | None = None
    criteria: tuple[LssScanCriterion, ...] = ()

