"""Train-to-train radio: the per-direction link model and the cangw-style gateway that routes frames over it."""
from hil.radio.gateway import RadioGateway, RadioIds, Route, build_links, standard_routes
from hil.radio.link import RadioLink

__all__ = ["RadioGateway", "RadioIds", "RadioLink", "Route", "build_links", "standard_routes"]
