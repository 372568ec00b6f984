"""Secrets and access control of an awaremw deployment (docs/security.md).

* :mod:`~awaremw.security.keys` -- ``awaremw keys init DIR``: the radio network
  key, the gateway's Ed25519 signing key pair, Zenoh credentials per role,
  the Zenoh router and client configs, Mosquitto password and ACL files;
* :mod:`~awaremw.security.zenoh_acl` -- the Zenoh access-control rules per role
  and the session settings a process uses to connect with its role.
"""
