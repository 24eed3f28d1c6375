"""What every stage reads: torch datasets over fppsim's readers (``datasets``), the reference splits
(``splits``) and the augmentation of synthetic samples (``augment``)."""
