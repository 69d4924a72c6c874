// BM_BulletSoftBody/<organ>: Bullet's soft body on the same mesh, step and iteration count as
// BM_PositionBased — the baseline of issue 4. (Placeholder: filled in by the Bullet helper.)
