"""Live tracking beside the press: MQTT in and out, a durable store and a live page.

The pieces, from the wire inwards:

* :mod:`~formtwin.service.messages` -- the versioned JSON messages (stroke in, estimate and
  error out) and their validation; every rejection carries a named reason.
* :mod:`~formtwin.service.store` -- SQLite (WAL): products keyed by part id, rejections, and
  the tracker checkpoint, all written in one transaction per message.
* :mod:`~formtwin.service.processor` -- the broker-free core: payload in, outcome out.
* :mod:`~formtwin.service.mqtt` -- paho-mqtt plumbing (QoS 1, manual acknowledgement after
  commit, username/password and TLS).
* :mod:`~formtwin.service.web` -- FastAPI page with Server-Sent Events and uPlot (shipped in
  ``static/``, MIT licence beside it).
* :mod:`~formtwin.service.streams` -- stroke streams: read a file, or make one from the
  analytic stand-in, for ``formtwin replay`` and the tests.

Nothing read from the network is ever unpickled or evaluated: messages are parsed with
:func:`json.loads` and checked field by field.
"""
