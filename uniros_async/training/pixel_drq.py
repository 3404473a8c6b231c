"""TD3 from pixels and proprioception: a small conv encoder shared by actor and critic, DrQ-style.

The agent of the pixel reach recipe (training/pixel_train.py, ``configs/rx200_reach_pixels_drq.yaml``). Each part
is a published method chosen for samples and compute on a CPU at one thread:

- **Encoder** (``SpatialSoftmaxEncoder``): two small convolutions and a spatial soft-argmax, which turns each of
  the last layer's feature maps into the expected image (x, y) of its activation (Levine et al. 2016, "End-to-End
  Training of Deep Visuomotor Policies", JMLR 17). A reach needs where the target is, and a keypoint says that in
  two numbers per channel; the features are joined by the arm's own state (proprioception), as in that paper.
- **Shared encoder trained by the critic only**: the actor reads the encoder's features detached (Yarats et al.
  2021, "Improving Sample Efficiency in Model-Free RL from Images" (SAC-AE); Kostrikov et al. 2021, "Image
  Augmentation Is All You Need" (DrQ)). The target critic has a target encoder, updated by Polyak averaging.
- **Random-shift augmentation** (DrQ): each image of a batch is padded by ``pad`` pixels (edge replicated) and
  cropped back at a random offset, for the observation and the next observation independently.
- **TD3** (Fujimoto et al. 2018): twin critics, target policy smoothing, delayed actor updates; with n-step
  returns as in DrQ-v2 (Yarats et al. 2022, "Mastering Visual Continuous Control").
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F  # noqa: N812 (torch's own spelling)
from torch import nn

__all__ = ["DrQConfig", "PixelTD3", "SpatialSoftmaxEncoder", "random_shift"]


@dataclass(frozen=True)
class DrQConfig:
    """The agent's sizes and TD3's hyperparameters (see PixelTrainConfig for their meaning)."""

    image_size: tuple[int, int]
    state_dim: int
    action_dim: int
    channels: int = 32
    hidden: int = 256
    lr: float = 3e-4
    gamma: float = 0.99
    tau: float = 0.01
    encoder_tau: float = 0.05
    policy_delay: int = 2
    target_noise: float = 0.2
    target_noise_clip: float = 0.5
    pad: int = 2


def random_shift(x: torch.Tensor, pad: int) -> torch.Tensor:
    """DrQ's random shift: pad each image of ``x`` (B, C, H, W) by ``pad`` pixels (edge replicated), then crop
    (H, W) back at a random integer offset per image."""
    if pad <= 0:
        return x
    b, _, h, w = x.shape
    padded = F.pad(x, (pad, pad, pad, pad), mode="replicate")
    dx = torch.randint(0, 2 * pad + 1, (b,))
    dy = torch.randint(0, 2 * pad + 1, (b,))
    rows = (dy[:, None] + torch.arange(h)[None, :])[:, None, :, None].expand(b, x.shape[1], h, w + 2 * pad)
    shifted = padded.gather(2, rows)
    cols = (dx[:, None] + torch.arange(w)[None, :])[:, None, None, :].expand(b, x.shape[1], h, w)
    return shifted.gather(3, cols)


class SpatialSoftmaxEncoder(nn.Module):
    """uint8 images (B, 3, H, W) -> keypoints (B, 2 x channels): the expected (x, y) in [-1, 1] of each feature map
    of two 3x3 convolutions (the first of stride 2), by a spatial softmax with a learned temperature."""

    def __init__(self, channels: int, image_size: tuple[int, int]) -> None:
        super().__init__()
        self.convs = nn.Sequential(
            nn.Conv2d(3, channels // 2, 3, stride=2),
            nn.ReLU(),
            nn.Conv2d(channels // 2, channels, 3),
        )
        with torch.no_grad():
            _, _, h, w = self.convs(torch.zeros(1, 3, *image_size)).shape
        ys, xs = torch.meshgrid(torch.linspace(-1, 1, h), torch.linspace(-1, 1, w), indexing="ij")
        self.register_buffer("grid", torch.stack([xs.reshape(-1), ys.reshape(-1)], dim=1))  # (h*w, 2)
        self.log_temperature = nn.Parameter(torch.zeros(()))
        self.out_dim = 2 * channels

    def forward(self, pixels: torch.Tensor) -> torch.Tensor:
        """Keypoints of ``pixels`` (uint8 or float in [0, 255])."""
        maps = self.convs(pixels.float() / 255.0 - 0.5)
        b, c = maps.shape[:2]
        attention = torch.softmax(maps.reshape(b, c, -1) / self.log_temperature.exp(), dim=-1)
        grid: torch.Tensor = self.grid  # type: ignore[assignment]
        return (attention @ grid).reshape(b, 2 * c)


def _mlp(inp: int, hidden: int, out: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Linear(inp, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, out)
    )


class _Critic(nn.Module):
    def __init__(self, feat: int, action_dim: int, hidden: int) -> None:
        super().__init__()
        self.q1 = _mlp(feat + action_dim, hidden, 1)
        self.q2 = _mlp(feat + action_dim, hidden, 1)

    def forward(self, h: torch.Tensor, a: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = torch.cat([h, a], dim=1)
        return self.q1(x), self.q2(x)


class PixelTD3(nn.Module):
    """TD3 over ``SpatialSoftmaxEncoder`` keypoints joined by the proprioceptive state (see the module docstring).

    Observations are (pixels (B, H, W, 3) uint8, state (B, state_dim) float32); actions in [-1, 1].
    """

    def __init__(self, cfg: DrQConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.encoder = SpatialSoftmaxEncoder(cfg.channels, cfg.image_size)
        self.encoder_target = SpatialSoftmaxEncoder(cfg.channels, cfg.image_size)
        feat = self.encoder.out_dim + cfg.state_dim
        self.actor = nn.Sequential(_mlp(feat, cfg.hidden, cfg.action_dim), nn.Tanh())
        self.actor_target = nn.Sequential(_mlp(feat, cfg.hidden, cfg.action_dim), nn.Tanh())
        self.critic = _Critic(feat, cfg.action_dim, cfg.hidden)
        self.critic_target = _Critic(feat, cfg.action_dim, cfg.hidden)
        for online, target in self._pairs():
            target.load_state_dict(online.state_dict())
            target.requires_grad_(False)
        self.actor_opt = torch.optim.Adam(self.actor.parameters(), lr=cfg.lr)
        self.critic_opt = torch.optim.Adam([*self.critic.parameters(), *self.encoder.parameters()], lr=cfg.lr)
        self.updates = 0

    def _pairs(self) -> list[tuple[nn.Module, nn.Module]]:
        return [
            (self.encoder, self.encoder_target),
            (self.actor, self.actor_target),
            (self.critic, self.critic_target),
        ]

    @staticmethod
    def _chw(pixels: torch.Tensor) -> torch.Tensor:
        return pixels.permute(0, 3, 1, 2)

    @torch.no_grad()
    def act(self, pixels: Any, state: Any) -> Any:
        """The deterministic actions (B, action_dim) as numpy for a batch of observations (numpy or tensors)."""
        px = torch.as_tensor(pixels)
        st = torch.as_tensor(state, dtype=torch.float32)
        h = torch.cat([self.encoder(self._chw(px)), st], dim=1)
        return self.actor(h).numpy()

    def update(self, batch: dict[str, torch.Tensor]) -> dict[str, float]:
        """One TD3 update on ``batch`` (pixels, state, action, reward, discount (gamma^n, 0 at a terminal),
        next_pixels, next_state); the actor and the targets every ``policy_delay`` updates. Returns the losses."""
        cfg = self.cfg
        px = random_shift(self._chw(batch["pixels"]).float(), cfg.pad)
        next_px = random_shift(self._chw(batch["next_pixels"]).float(), cfg.pad)
        with torch.no_grad():
            h_next = torch.cat([self.encoder_target(next_px), batch["next_state"]], dim=1)
            noise = (torch.randn_like(batch["action"]) * cfg.target_noise).clamp(
                -cfg.target_noise_clip, cfg.target_noise_clip
            )
            a_next = (self.actor_target(h_next) + noise).clamp(-1.0, 1.0)
            q1_t, q2_t = self.critic_target(h_next, a_next)
            target = batch["reward"] + batch["discount"] * torch.min(q1_t, q2_t)
        h = torch.cat([self.encoder(px), batch["state"]], dim=1)
        q1, q2 = self.critic(h, batch["action"])
        critic_loss = F.mse_loss(q1, target) + F.mse_loss(q2, target)
        self.critic_opt.zero_grad(set_to_none=True)
        critic_loss.backward()  # type: ignore[no-untyped-call]
        self.critic_opt.step()
        out = {"critic_loss": float(critic_loss.detach()), "q": float(q1.detach().mean())}
        self.updates += 1
        if self.updates % cfg.policy_delay == 0:
            hd = h.detach()
            actor_loss = -self.critic.q1(torch.cat([hd, self.actor(hd)], dim=1)).mean()
            self.actor_opt.zero_grad(set_to_none=True)
            actor_loss.backward()
            self.actor_opt.step()
            out["actor_loss"] = float(actor_loss.detach())
            with torch.no_grad():
                for (online, target), tau in zip(self._pairs(), (cfg.encoder_tau, cfg.tau, cfg.tau), strict=True):
                    for p, pt in zip(online.parameters(), target.parameters(), strict=True):
                        pt.lerp_(p, tau)
        return out

    def training_state(self) -> dict[str, Any]:
        """Everything to resume: the networks, the optimisers and the update count."""
        return {
            "model": self.state_dict(),
            "actor_opt": self.actor_opt.state_dict(),
            "critic_opt": self.critic_opt.state_dict(),
            "updates": self.updates,
        }

    def load_training_state(self, state: dict[str, Any]) -> None:
        """Restore what ``training_state`` gave."""
        self.load_state_dict(state["model"])
        self.actor_opt.load_state_dict(state["actor_opt"])
        self.critic_opt.load_state_dict(state["critic_opt"])
        self.updates = int(state["updates"])
