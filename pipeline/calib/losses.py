"""The thesis's switched losses of a sensor group's networks (eqs. 5.4-5.12), on torch tensors.

Losses (`switched_loss`), per sample i, averaged over the batch (thesis eqs. 5.4-5.12):

    L_i = sum_s alpha_si lambda_s mse(f_si^exp - f_si^NN)
          + alpha_sum,i lambda_sum mse(sum_s X_s f_si^exp - sum_s X_s f_si^NN)

where mse is the mean over the 6 components, alpha_si the exact-label switch of sensor s (eq. 5.5, 5.11),
X_s the 6x6 wrench transform ``sole_X_s`` and alpha_sum = sw_pair (1 - prod_s sw_s) (eq. 5.12). With one
sensor and no sum this is eq. 5.4; for a foot it is L_front + L_rear of eqs. 5.6-5.7 with the sum term
counted once, whose gradient with respect to each network is exactly that of its own eq. 5.6 or 5.7.
"""

from __future__ import annotations

import torch


def _switched_mse(error: torch.Tensor, switch: torch.Tensor) -> torch.Tensor:
    """Per-sample mse over the last axis (6) where `switch` (bool) is set, 0 elsewhere.

    Labels are NaN where their switch is 0: the error is masked with `torch.where` (NaN * 0 is NaN).
    """
    masked = torch.where(switch.unsqueeze(-1), error, torch.zeros((), dtype=error.dtype))
    return masked.square().mean(dim=-1)


def sum_in_sole(wrenches: torch.Tensor, transforms: torch.Tensor) -> torch.Tensor:
    """sum_s X_s f_s of eqs. 5.9-5.10, in the sole frame: (B, 6).

    wrenches (B, S, 6) in their sensor frames; transforms (S, 6, 6) ``sole_X_s``.
    """
    return torch.einsum("sij,bsj->bi", transforms.to(wrenches.dtype), wrenches)


def switched_loss(
    pred: torch.Tensor,
    labels: torch.Tensor,
    switches: torch.Tensor,
    lambdas: torch.Tensor,
    sum_label: torch.Tensor | None = None,
    alpha_sum: torch.Tensor | None = None,
    transforms: torch.Tensor | None = None,
    lambda_sum: float = 1.0,
    cuts: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None,
    lambda_cut: float = 1.0,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """The thesis's switched loss, averaged over the batch (module docstring; eqs. 5.4-5.12).

    Args:
        pred: (B, S, 6) network outputs, N and Nm, each in its sensor frame.
        labels: (B, S, 6) expected wrenches (NaN allowed where the switch is 0).
        switches: (B, S) bool, alpha_s (eq. 5.5, 5.11).
        lambdas: (S,) weights lambda_s.
        sum_label: (B, 6) expected sum in the sole frame (NaN allowed where alpha_sum is 0), or None.
        alpha_sum: (B,) bool, the sum switch of eq. 5.12 (already sw_pair * (1 - prod sw_s)), or None.
        transforms: (S, 6, 6) ``sole_X_s``; required with sum_label.
        lambda_sum: weight of the sum term.
        cuts: (predicted sums (B, C, 6), labels (B, C, 6), switches (B, C) bool) of cut sets
            (`pipeline.calib.cuts`), or None: one term per cut set, alpha lambda_cut mse, like the sum's.
        lambda_cut: weight of each cut-set term.

    Returns:
        (total loss, {"s0": term, "s1": term, "sum": term}): each term is the batch mean of
        alpha lambda mse, so that total = sum of the terms.
    """
    per_sensor = _switched_mse(pred - labels, switches) * lambdas  # (B, S)
    terms = {f"s{s}": per_sensor[:, s].mean() for s in range(pred.shape[1])}
    total = per_sensor.sum(dim=1)
    if sum_label is not None:
        if alpha_sum is None or transforms is None:
            raise ValueError("sum_label needs alpha_sum and transforms")
        sum_term = _switched_mse(sum_in_sole(pred, transforms) - sum_label, alpha_sum) * lambda_sum
        terms["sum"] = sum_term.mean()
        total = total + sum_term
    if cuts is not None:
        cut_pred, cut_label, cut_alpha = cuts
        per_cut = _switched_mse(cut_pred - cut_label, cut_alpha) * lambda_cut  # (B, C)
        terms.update({f"c{c}": per_cut[:, c].mean() for c in range(per_cut.shape[1])})
        total = total + per_cut.sum(dim=1)
    return total.mean(), terms
