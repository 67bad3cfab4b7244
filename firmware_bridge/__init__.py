"""firmware_bridge: the AgileX UGV CAN protocol V2 and the link to the robot base.

* ``agilex_v2.dbc``: frame layouts, the single source of truth (read with cantools).
* ``protocol``: frame ids, constants and the typed records.
* ``codec``: SDK-exact ``encode``, ``decode`` / ``FrameDecoder`` (frame faults rejected,
  out-of-range feedback fields flagged).
* ``frame_errors``: ``FrameError`` and its named subclasses.
* ``candump``: candump text in and out.
* ``buses``: ``BusConfig`` / ``open_bus`` (virtual, udp_multicast, socketcan, limo_serial).
* ``limo_serial``: the LIMO UART framing as a python-can bus.
* ``base_driver``: ``AgileXBaseDriver`` (enable, 0x111 from the caller's loop, feedback staleness, stop).
* ``cli``: the ``dct can`` command group.
"""
