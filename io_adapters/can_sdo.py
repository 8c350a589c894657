"""The SDO server of a CiA 402 node (:mod:`io_adapters.can_node`): canopen's
:class:`~canopen.sdo.SdoServer` for the transfers themselves (through
:class:`canopen.LocalNode`'s object dictionary and the node's callbacks), with what
canopen 2.4 leaves unchecked checked first, so that every request is answered as CiA 301
has it and none raises or logs.

* **The multiplexer** of an initiate request must name an object of the catalog
  (:func:`~io_adapters.can_catalog.spec`): 0602 0000h for an index the dictionary does not
  have, 0609 0011h for a sub-index its object does not have, before its access or the
  data's length is looked at.  canopen would look sub-indices up in its own dictionary,
  where an array (:class:`~canopen.objectdictionary.ODArray`: 607Dh, 6091h, 6092h ...)
  answers every sub-index 1-255 with a copy of its first member, and a variable any
  sub-index with itself.
* **The command specifier**: a download segment outside a segmented download, an upload
  segment (the catalog's objects are 1 to 4 bytes: every upload is expedited), a block
  transfer (not offered: the EDS does not declare it) and the reserved specifier 7 are
  aborted with 0504 0001h.  canopen would answer a segment from whatever its last
  transfer left behind, or raise (a ``TypeError`` for a segment before any transfer) and
  log the traceback.
* **A segmented download** longer than the object it writes is aborted with 0607 0012h at
  the segment that makes it so: the data held for one transfer stay bounded whatever a
  master sends.

An abort carries the multiplexer of the request it answers (for a segment, the one of the
initiate request before it; 0000h:00 before any) and ends any transfer in progress; a
master's abort (80h) ends it without an answer.  The frame's length (8 bytes) is the
node's to check (:meth:`~io_adapters.can_node.DriveNode.on_sdo_request`).
"""

from canopen.sdo import SdoAbortedError, SdoServer
from canopen.sdo.constants import (
    EXPEDITED,
    NO_MORE_DATA,
    REQUEST_ABORTED,
    REQUEST_DOWNLOAD,
    REQUEST_SEGMENT_DOWNLOAD,
    REQUEST_SEGMENT_UPLOAD,
    REQUEST_UPLOAD,
    RESPONSE_ABORTED,
    SDO_STRUCT,
)

from io_adapters.can_catalog import (
    BITS,
    SDO_ABORT_COMMAND,
    SDO_ABORT_LENGTH_HIGH,
    SDO_ABORT_NO_OBJECT,
    SDO_ABORT_NO_SUBINDEX,
    spec,
)

#: the bytes of every SDO frame (CiA 301)
SDO_FRAME_BYTES = 8
#: the bytes a download segment carries at most
SEGMENT_BYTES = 7
COMMAND_SPECIFIER = 0xE0


def multiplexer_abort(index: int, subindex: int) -> int:
    """The abort code for a request naming ``index``:``subindex``, 0 if the catalog has
    it."""
    if spec(index, subindex) is not None:
        return 0
    return SDO_ABORT_NO_OBJECT if spec(index, 0) is None else SDO_ABORT_NO_SUBINDEX


class NodeSdoServer(SdoServer):
    """canopen's SDO server behind the checks of the module docstring.

    Args:
        rx_cobid, tx_cobid: the COB-IDs of requests and responses (600h/580h + node-ID).
        node: the :class:`canopen.LocalNode` whose dictionary it serves.

    Attributes:
        multiplexer: (index, sub-index) an abort carries.
        download_left: bytes the segmented download in progress may still bring (the
            object's size less those received), or None when none is in progress.
    """

    def __init__(self, rx_cobid: int, tx_cobid: int, node):
        super().__init__(rx_cobid, tx_cobid, node)
        self.multiplexer = (0, 0)
        self.download_left: int | None = None

    def on_request(self, can_id: int, data: bytearray, timestamp: float) -> None:
        """Serve one request of :data:`SDO_FRAME_BYTES` bytes (the node checked it)."""
        try:
            self._serve(bytes(data))
        except SdoAbortedError as e:
            self.abort(e.code)

    def _serve(self, request: bytes) -> None:
        command = request[0]
        specifier = command & COMMAND_SPECIFIER
        if specifier in (REQUEST_UPLOAD, REQUEST_DOWNLOAD):
            _, index, subindex = SDO_STRUCT.unpack_from(request)
            self.download_left, self.multiplexer = None, (index, subindex)
            code = multiplexer_abort(index, subindex)
            if code:
                raise SdoAbortedError(code)
            if specifier == REQUEST_UPLOAD:
                self.init_upload(request)
            else:
                self.init_download(request)
                if not command & EXPEDITED:
                    self.download_left = BITS[spec(index, subindex).data_type] // 8
        elif specifier == REQUEST_SEGMENT_DOWNLOAD and self.download_left is not None:
            self.download_left -= SEGMENT_BYTES - (command >> 1 & 0x7)
            if self.download_left < 0:
                raise SdoAbortedError(SDO_ABORT_LENGTH_HIGH)
            self.segmented_download(command, request)
            if command & NO_MORE_DATA:
                self.download_left = None
        elif specifier == REQUEST_ABORTED:
            self.download_left = None
        else:  # a segment out of place, a block transfer, the reserved specifier 7
            if specifier not in (REQUEST_SEGMENT_DOWNLOAD, REQUEST_SEGMENT_UPLOAD):
                self.multiplexer = SDO_STRUCT.unpack_from(request)[1:]
            raise SdoAbortedError(SDO_ABORT_COMMAND)

    def abort(self, abort_code: int) -> None:
        """Answer the abort ``abort_code`` with :attr:`multiplexer`; no transfer is left in
        progress."""
        self.download_left = None
        index, subindex = self.multiplexer
        self.send_response(SDO_STRUCT.pack(RESPONSE_ABORTED, index, subindex)
                           + abort_code.to_bytes(4, "little"))
