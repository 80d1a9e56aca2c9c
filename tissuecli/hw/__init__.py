"""Devices on the line: the wire protocol (:mod:`~tissuecli.hw.protocol`), serial links
and the one open-and-identify handshake (:mod:`~tissuecli.hw.link`, the only pyserial
importer), the acquisition-loop skeleton (:mod:`~tissuecli.hw.stream`) and real-time
primitives (:mod:`~tissuecli.hw.realtime`)."""
