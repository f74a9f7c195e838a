"""Cards whose contents reach the browser when first opened.

A page's server cost is mostly the Bokeh models Panel makes for it (about 1 ms each, 300+ on the
dashboard; see the review issue's "sessions are cheap"), and a collapsed card's models are made
and sent even though nobody sees them until the card is opened. :func:`lazy_card` keeps the
Python objects (widgets keep their values and watchers, code may read and set them) and puts
them into the card only when a user first opens it: the models are then made for that page alone.
"""

from __future__ import annotations

import panel as pn

__all__ = ["lazy_card", "fill"]


def lazy_card(*objects, collapsed: bool = True, **params) -> pn.Card:
    """A :class:`panel.Card` of ``objects``; when ``collapsed`` it starts empty and takes them the
    first time it is opened (in the browser or by setting ``card.collapsed = False``)."""
    if not collapsed:
        return pn.Card(*objects, collapsed=False, **params)
    card = pn.Card(collapsed=True, **params)
    card._lazy_objects = list(objects)

    def _open(event):
        if not event.new:
            fill(card)

    card._lazy_watcher = card.param.watch(_open, "collapsed")
    return card


def fill(card: pn.Card) -> pn.Card:
    """Put a lazy card's objects into it now (a no-op for a card already filled or not lazy)."""
    objects = getattr(card, "_lazy_objects", None)
    if objects is not None:
        card._lazy_objects = None
        card.param.unwatch(card._lazy_watcher)
        card.objects = objects
    return card
