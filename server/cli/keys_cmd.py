"""``crowdslam keys create|list|revoke``: mint a key from the command line (the first operator key comes from
here), list keys with their last use, revoke one by its prefix (site-wide keys, or ``--building``'s)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING

from server.cli.user_errors import UserError

if TYPE_CHECKING:
    from sqlalchemy.orm import Session


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="action", required=True, metavar="ACTION")
    create = sub.add_parser("create", help="mint a key and print it on the last line")
    create.add_argument("--scope", required=True, choices=["operator", "device", "dashboard"])
    create.add_argument("--building", help="the key's building (required for device and dashboard keys)")
    create.add_argument("--device", help="the device id of a device key")
    listing = sub.add_parser("list", help="list keys (never their secrets) with their last use")
    listing.add_argument("--building", help="a building's keys (default: the site-wide operator keys)")
    revoke = sub.add_parser("revoke", help="revoke a key by its prefix")
    revoke.add_argument("prefix")
    revoke.add_argument("--building", help="the key's building (default: a site-wide key)")


def run(args: argparse.Namespace) -> int:
    if args.action in ("list", "revoke"):
        return _list_or_revoke(args)
    # deferred: the command's dependencies load when it runs (`crowdslam --help` loads none)
    from schemas.api import KeyScope
    from server.auth import mint_key

    scope = KeyScope(args.scope)
    if scope != KeyScope.OPERATOR and args.building is None:
        print(f"error: a {scope.value} key needs --building", file=sys.stderr)
        return 2
    if (scope == KeyScope.DEVICE) != (args.device is not None):
        print("error: --device is required for a device key and only allowed for one", file=sys.stderr)
        return 2
    try:
        with _key_store(args.building) as session:
            secret, prefix = mint_key(session, scope, args.building, args.device)
    except UserError as error:
        print(f"error: {error}", file=sys.stderr)
        return 1
    where = f" for building {args.building}" if args.building else " (all buildings)"
    print(f"{scope.value} key {prefix}{where}; it is shown only once:")
    print(secret)
    return 0


@contextmanager
def _key_store(building: str | None) -> Iterator[Session]:
    """A transaction on the settings' database, once it is migrated and has the building (if one is named)."""
    # deferred: the command's dependencies load when it runs (`crowdslam --help` loads none)
    from server.settings import get_settings
    from server.store import repositories as repo
    from server.store.db import make_engine, make_session_factory
    from server.store.migrate import current_revision, head_revision

    engine = make_engine(get_settings().resolved_database_url)
    try:
        if current_revision(engine) != head_revision(engine):
            raise UserError("the database is not migrated; run `crowdslam migrate` first")
        with make_session_factory(engine).begin() as session:
            if building is not None and repo.get_building(session, building) is None:
                raise UserError(f"no building {building!r}")
            yield session
    finally:
        engine.dispose()


def _list_or_revoke(args: argparse.Namespace) -> int:
    # deferred: the command's dependencies load when it runs (`crowdslam --help` loads none)
    from server.api.buildings import key_info
    from server.store import repositories as repo

    with _key_store(args.building) as session:
        if args.action == "revoke":
            if not repo.revoke_keys(session, args.building, args.prefix):
                where = f"building {args.building!r}" if args.building else "the site-wide keys"
                raise UserError(f"no live key {args.prefix!r} among {where}")
            print(f"revoked {args.prefix}; servers refuse it within their key cache's lifetime")
            return 0
        for row in repo.list_keys(session, args.building):
            key = key_info(row)
            used = key.last_used_at.isoformat() if key.last_used_at else "never"
            state = f"revoked {key.revoked_at.isoformat()}" if key.revoked_at else "live"
            device = f" device {key.device_id}" if key.device_id else ""
            print(
                f"{key.prefix}  {key.scope.value}{device}  created {key.created_at.isoformat()}  "
                f"last used {used}  {state}"
            )
    return 0
