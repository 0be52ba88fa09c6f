"""``GET /api/machines/{machine}/trend?limit=N``: a machine's trend as JSON for the operator
page's chart (``daemon.reports.trend.trend_series``: per link its unit, values and limits)."""

from __future__ import annotations

from aiohttp import web

from daemon.hmi.limits import int_param
from daemon.reports.trend import trend_series

TREND_DEFAULT, TREND_MAX = 30, 200


def trend_handler(sessions_key: web.AppKey, store_key: web.AppKey) -> object:
    """The handler, bound to the app's keys for the sessions and the store."""

    async def trend(request: web.Request) -> web.Response:
        name = request.match_info["machine"]
        session = request.app[sessions_key].get(name)
        if session is None:
            raise web.HTTPNotFound(text=f"no machine {name!r}")
        limit = int_param(request, "limit", TREND_DEFAULT, 2, TREND_MAX)
        points = request.app[store_key].trend(name, limit)
        return web.json_response({"machine": name,
                                  **trend_series(points, session.setup.tolerances)})

    return trend
