"""Social-GAN (Gupta et al., CVPR 2018), a comparison row of the paper's tables (issue 63): ``config``
(``SocialGanConfig``, presets ``social_gan_20v`` and ``social_gan_20vp``), ``net`` (generator with the pooling
module, local discriminator), ``fit`` (variety and adversarial losses, the training iteration, sampling), ``predictor``
(``SocialGanPredictor``). Trained with ``logpipe train --preset social_gan_20v|social_gan_20vp``.

Settings, and where they come from. The paper (§3.6): embedding 16, encoder LSTM hidden 16, decoder hidden 32,
batch 64, Adam with learning rate 1e-3; variety loss with k = 20 (the "20V" of the variant names), 20 samples at
test ("-20"); 8 observed and 12 predicted steps (here: the dataset's protocol). The official repository's
``scripts/run_traj.sh``: noise 8-dimensional Gaussian, one draw per scene ('global' mix, so a sample is a joint
forecast), pooling once after the observed steps (``pool_every_timestep`` 0), pooling MLP 512 -> bottleneck 32
(``bottleneck_dim``), context MLP width 64 (``mlp_dim``), discriminator hidden 64 of type 'local', l2 (variety) loss
weight 1, 2 discriminator steps per generator step, generator gradients clipped at norm 1.5, no batch norm, no
dropout; its ``models.py``: Kaiming-normal initialisation of linear layers; its ``losses.py``: labels smoothed to
U(0.7, 1.2) for real and U(0, 0.3) for fake; the variety loss is the minimum over the k samples of each sequence's
summed squared step error.

Where this deviates, and why:

* ``run_traj.sh`` says batch 32, encoder hidden 32 and k = 10; the paper says batch 64 and encoder hidden 16 and the
  variant is named for k = 20: the paper's figures are taken.
* Iterations: ``run_traj.sh`` runs 20,000 (``steps`` here); a run stops earlier when the validation ADE (joint
  best-of-20 on at most ``val_windows`` windows of the split's ``/val``, checked every ``val_every`` iterations) has
  not improved ``patience`` times, and ``best/`` is the checkpoint of the lowest one. The published code selects on a
  single sample's validation ADE; best-of-20 is the rule the tables score, so it is the one selected on.
* **20VP-20 with batch norm** (``pool_batch_norm``, ``context_batch_norm``, on in the ``social_gan_20vp`` preset;
  ``run_traj.sh`` sets ``batch_norm 0``): without it 20VP-20 collapsed to one forecast. The pooling MLP embeds raw
  relative positions (metres, tens of them in UNIV's crowds) through Kaiming-initialised 512-wide layers, and on
  ``zara1/val`` its pooled vectors averaged 15.7 against the encoder's 0.17, so the decoder's initial context
  (mean 21.7, 13 of 24 units dead) drowned the N(0, 1) noise: the 20 samples' final positions lay 0.024 m apart
  (20V-20: 1.9 m). Batch norm after each hidden layer of the pooling and context MLPs is the published code's own
  ``batch_norm`` option (its ``make_mlp``; the discriminator keeps none). Measured with
  ``scripts/social_variety.py`` on 200 ``zara1/val`` windows: in the pooling MLP alone, the context still averaged
  1.9 and the samples 0.28 m apart at iteration 300; in both MLPs, context 0.47 with no dead unit, samples 0.69 m
  apart and joint best-of-20 ADE 1.41 m at iteration 350 (without: 1.91 m; ``docs/results/ethucy_social.md``).
  Set both false for the published setting.
* The discriminator's last layer has no ReLU (the published MLP helper puts one after every layer, which clamps
  the logit at 0).
* A window's agents are those observed over its whole window in training (as the published loader keeps), and those
  observed at the current step at prediction, history gaps filled (``model.training.social_batch``): the published
  evaluation also selects agents by their future, which a forecast cannot.

Imports: core, ``model.training``, ``model.checkpoint``; never another family.
"""
