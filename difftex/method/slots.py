"""A level's top-K slots: per texel, the K best candidate photos and their values (visibility,
compared colours, Q, the persp cost, the starting weight; the full-detail colours and the
blend's Q where the level keeps them), filled one photo at a time.

Every texel keeps only its K best candidates, so a level's tensors grow with texels x K, not
texels x photos (difftex.method.levels).
"""

from __future__ import annotations

import torch

from difftex.sampling.texels import Region

EMPTY_SCORE = -10.0  # below any candidate's score: an empty slot


def _per_slot(m: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """A (K, h, w) map shaped to index or mask ``t`` (K, [C,] h, w)."""
    return m if t.dim() == 3 else m[:, None].expand(-1, t.shape[1], -1, -1)


class Slots:
    """The slot tensors of one level, and how a photo's values enter them.

    Args:
        K: slots per texel.
        shape: the level's (h, w).
        device: the torch device.
        detail: whether the slots keep the full-detail colours beside the compared ones.
        blend_q: whether the slots keep the blend's Q beside the witnesses' Q.

    Fields: ``idx`` (K, h, w) long, the photo of each slot (-1: none), ``visible`` (K, h, w) bool,
    ``colours`` (K, 3, h, w), ``Q``, ``cost``, ``w0`` (K, h, w), ``detail`` (K, 3, h, w) or None,
    ``Qb`` (K, h, w) or None, ``resolve`` (K, h, w) or None (pixels per texel x cos^2, for the
    detail, difftex.method.detail). A photo's values are given in the order of ``data``.
    """

    def __init__(
        self, K: int, shape: tuple[int, int], device, detail: bool, blend_q: bool, resolve: bool = False
    ) -> None:
        h, w = shape
        self.K = K
        self.score = torch.full((K, h, w), EMPTY_SCORE, device=device)
        self.idx = torch.full((K, h, w), -1, dtype=torch.long, device=device)
        self.visible = torch.zeros((K, h, w), dtype=torch.bool, device=device)
        self.colours = torch.zeros((K, 3, h, w), device=device)
        self.detail = torch.zeros((K, 3, h, w), device=device) if detail else None
        self.Q = torch.zeros((K, h, w), device=device)
        self.cost = torch.zeros((K, h, w), device=device)
        self.w0 = torch.zeros((K, h, w), device=device)
        self.Qb = torch.zeros((K, h, w), device=device) if blend_q else None
        self.resolve = torch.zeros((K, h, w), device=device) if resolve else None
        self.data = [self.visible, self.colours, self.Q, self.cost, self.w0]
        self.data += [t for t in (self.detail, self.Qb, self.resolve) if t is not None]
        # (photo, region) -> its values, written once the ranking is final (``write_deferred``)
        self.deferred: dict[tuple[int, Region], list[torch.Tensor]] = {}

    def pack(
        self, visible: torch.Tensor, colours: torch.Tensor, Q: torch.Tensor, cost: torch.Tensor, w0: torch.Tensor,
        detail: torch.Tensor, Qb: torch.Tensor, resolve: torch.Tensor | None = None,
    ) -> list[torch.Tensor]:
        """A photo's values in the order of ``data``, without those the slots do not keep."""
        kept = [(detail, self.detail), (Qb, self.Qb), (resolve, self.resolve)]
        out = [visible, colours, Q, cost, w0]
        for v, t in kept:
            if t is not None:
                if v is None:
                    raise ValueError("the slots keep a value the photo was not given")
                out.append(v)
        return out

    def put(self, j: int, n: int, reg: Region, values: list[torch.Tensor]) -> None:
        """Photo ``n`` into slot ``j`` over ``reg`` (every candidate fits: slot j is photo j)."""
        y0, y1, x0, x1 = reg
        self.idx[j][y0:y1, x0:x1] = n
        for t, new in zip(self.data, values):
            t[j, ..., y0:y1, x0:x1] = new

    def rank(self, n: int, reg: Region, score: torch.Tensor, values: list[torch.Tensor], defer: bool) -> None:
        """Photo ``n`` as the (K + 1)-th candidate of the texels of ``reg``: the K best scores stay.

        Args:
            n: the photo.
            reg: (y0, y1, x0, x1) its region.
            score: (rh, rw) its ranking score there.
            values: its values, in the order of ``data``.
            defer: keep the values and write them once every photo is ranked
                (``write_deferred``: one pass of masked writes instead of gathering every slot
                tensor for every photo); else gather them into the slots now.
        """
        y0, y1, x0, x1 = reg
        top = torch.topk(torch.cat([self.score[:, y0:y1, x0:x1], score[None]]), self.K, dim=0)
        sel = top.indices

        def pick(old: torch.Tensor, new: torch.Tensor) -> torch.Tensor:
            """``old`` (K, [C,] h, w) ranked with the photo's ``new`` as the (K + 1)-th candidate."""
            return torch.gather(torch.cat([old, new[None]]), 0, _per_slot(sel, old))

        self.score[:, y0:y1, x0:x1] = top.values
        self.idx[:, y0:y1, x0:x1] = pick(self.idx[:, y0:y1, x0:x1], torch.full_like(score, n, dtype=torch.long))
        if defer:
            self.deferred[(n, reg)] = values
            return
        for t, new in zip(self.data, values):
            t[..., y0:y1, x0:x1] = pick(t[..., y0:y1, x0:x1], new)

    def write_deferred(self) -> None:
        """Write the deferred photos' values where the final ranking put them."""
        for (n, reg), values in self.deferred.items():
            y0, y1, x0, x1 = reg
            # (slot, y, x) of every texel where photo n holds a slot (at most one slot per texel): its
            # values are scattered there, not blended in by a where over every slot of its region
            js, ys, xs = (self.idx[:, y0:y1, x0:x1] == n).nonzero(as_tuple=True)
            if ys.numel() == 0:
                continue
            for t, new in zip(self.data, values):
                if t.dim() == 3:
                    t[js, ys + y0, xs + x0] = new[ys, xs]
                else:
                    t[js, :, ys + y0, xs + x0] = new[:, ys, xs].T
        self.deferred.clear()
