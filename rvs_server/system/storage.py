"""`products [--prune] [--dry-run]`: the products with their sizes, and the retention rule on demand.

The rule itself, what it protects and the storage cap live in rvs_server/products/retention.py.
"""
from __future__ import annotations

import asyncio
import time
from typing import Any

from pydantic import Field

from rvs_server.config import CommandConfig
from rvs_server.dispatch import Call
from rvs_server.products import retention
from rvs_server.protocol import BadRequest
from rvs_server.system.commands import module


class ProductsConfig(CommandConfig):
    prune: bool = Field(False, description="apply the retention rule (server.toml [storage]) now")
    dry_run: bool = Field(False, description="with --prune: say what it would remove, remove nothing")


@module.immediate("products", ProductsConfig)
def products(call: Call, cfg: ProductsConfig):
    """The products with their sizes and totals; --prune applies the retention rule (--dry-run: what it would)."""
    if cfg.dry_run and not cfg.prune:
        raise BadRequest("products: --dry-run goes with --prune (products --prune --dry-run)")
    server = call.server

    def work() -> dict[str, Any]:   # a walk of the products folder: in a thread, the transports go on
        report = retention.prune(server, "products --prune", dry_run=cfg.dry_run) if cfg.prune else None
        infos = retention.list_products(server.products.root)
        protected = retention.protected_products(server, infos)
        settings: retention.StorageSettings = server.settings.storage
        now = time.time()
        total = sum(p.bytes for p in infos)
        data: dict[str, Any] = {
            "count": len(infos), "bytes": total, "size": retention.human_bytes(total),
            "protected": len(protected),
            "max_gib": f"{settings.max_gib:g}", "max_days": f"{settings.max_days:g}",
            "cap_gib": f"{settings.cap_gib:g}",
            "free": retention.human_bytes(retention.free_space(server.products.root, server.products.root,
                                                              retention.files.storage_cap(server.products.root))),
        }
        if report is not None:
            data["dry_run"] = int(cfg.dry_run)
            key = "would_remove" if cfg.dry_run else "removed"
            data[key] = len(report.removed)
            data["freed_bytes" if not cfg.dry_run else "would_free_bytes"] = report.freed_bytes
            data[f"{key}.names"] = " ".join(p.name for p in report.removed) or "none"
        # newest first: p.NAME="BYTES COMMAND STATUS AGE_DAYS [KEPT_BECAUSE]"
        for info in reversed(infos):
            words = [str(info.bytes), info.command or "-", info.status, f"{info.age_days(now):.2f}d"]
            if info.name in protected:
                words.append(f"keep={protected[info.name]}")
            data[f"p.{info.name}"] = " ".join(words)
        return data

    return asyncio.to_thread(work)
