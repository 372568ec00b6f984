"""The gateway: bridge between the emulated WSN and IP devices (MQTT, Zenoh).

Modules (see docs/gateway.md):

* :mod:`~awaremw.gateway.schema` -- IP-side JSON -> radio definitions, specific refusals;
* :mod:`~awaremw.gateway.store` -- SQLite store of item versions (survive restarts);
* :mod:`~awaremw.gateway.bridge` -- the transport-independent gateway logic (sans-IO);
* :mod:`~awaremw.gateway.events` -- its actions (Publish, Inject, Report, ...) and Transport;
* :mod:`~awaremw.gateway.mqtt` -- aiomqtt connection, reconnect loop, outage buffer;
* :mod:`~awaremw.gateway.hbn` -- the Zenoh HBN API under ``<prefix>/hbn/**``;
* :mod:`~awaremw.gateway.broker` -- embedded amqtt broker for the demo;
* :mod:`~awaremw.gateway.service` -- wiring: gateway motes + bridge + transports
  (:func:`~awaremw.gateway.service.attach_to_fleet`).

Nothing is imported here, so that ``import awaremw.gateway.schema`` stays light.
"""
