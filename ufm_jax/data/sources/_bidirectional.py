"""Indexing shared by sources whose pairs have real ground truth in both directions."""

from __future__ import annotations


class BidirectionalPairs:
  """Mixin over `self.pairs` and `self._load(k, backward, images=None)`.

  `directions="forward"`: index k is pair k forward and `backward(k)` its backward pair.
  `directions="both"`: index 2k is pair k forward and 2k+1 its backward pair (`backward` swaps them).
  """

  directions: str = "forward"

  def _pair_and_direction(self, index: int) -> tuple[int, bool]:
    if self.directions == "both":
      return index // 2, bool(index % 2)
    return index, False

  def __len__(self):
    return len(self.pairs) * (2 if self.directions == "both" else 1)

  def __getitem__(self, index: int) -> dict:
    k, rev = self._pair_and_direction(index)
    return self._load(k, backward=rev)

  def backward(self, index: int) -> dict:
    """The pair of `index` with source and target swapped, labelled by the backward ground truth."""
    k, rev = self._pair_and_direction(index)
    return self._load(k, backward=not rev)

  def both(self, index: int) -> tuple[dict, dict]:
    """(`self[index]`, `self.backward(index)`) reading each image once (for symmetrised batches)."""
    k, rev = self._pair_and_direction(index)
    first = self._load(k, backward=rev)
    second = self._load(k, backward=not rev, images=(first["image1"].copy(), first["image0"].copy()))
    return first, second
