"""Thin routers under /v1: parse, authorise, call a service, shape the answer."""
