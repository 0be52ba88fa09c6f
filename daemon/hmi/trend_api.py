"""``GET /api/machines/{machine}/trend?limit=N``: a machine's trend as JSON for the operator
page's chart (``daemon.reports.trend.trend_series``: per link its unit, values and limits), its
temperature channels, and with ``&against=CHANNEL&link=EX0C`` a link error against that
recorded temperature, one point per run with r and the slope ± u."""

from __future__ import annotations

from aiohttp import web

from daemon.analysis.temperature_trend import fit, points
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
        rows = request.app[store_key].trend(name, limit)
        channels = [ch.name for ch in session.setup.temperatures]
        out = {"machine": name, **trend_series(rows, session.setup.tolerances),
               "channels": channels}
        against, link = request.query.get("against"), request.query.get("link")
        if against is not None or link is not None:
            out["against"] = _against(rows, against, link, channels,
                                      session.setup.machine.location_error_names())
        return web.json_response(out)

    return trend


def _against(rows: list, channel: str | None, link: str | None, channels: list[str],
             links: list[str]) -> dict:
    """The link against the channel over ``rows`` (store.trend): points and the fit; 400 with
    the reason for a channel or link the machine does not have."""
    if channel not in channels:
        raise web.HTTPBadRequest(text=f"against: {channel!r} is not a temperature channel of "
                                      f"this machine ({', '.join(channels) or 'none'})")
    if link not in links:
        raise web.HTTPBadRequest(text=f"link: {link!r} is not a location error of this machine")
    pts, unit = points(rows, link, channel)
    f = fit(pts, unit or ("µrad" if link[1] in "ABC" else "µm"))
    return {"channel": channel, "link": link, "unit": unit,
            "points": [{"run_id": p.run_id, "temperature_c": p.temperature_c,
                        "value": p.value, "std": p.std} for p in pts],
            "n": f.n, "r": f.r, "slope": f.slope, "slope_std": f.slope_std,
            "slope_u95": f.slope_u95,
            "slope_unit": f.unit, "text": f.text(link, channel)}
