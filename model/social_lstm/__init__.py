"""Social-LSTM (Alahi et al., CVPR 2016), a comparison row of the paper's tables (issue 63): ``config``
(``SocialLstmConfig``, preset ``social_lstm``), ``net`` (the per-agent LSTM, the social pooling grid of neighbours'
hidden states, the bivariate Gaussian output and its negative log-likelihood), ``fit`` (training, forecasts),
``predictor`` (``SocialLstmPredictor``: K = 1 the mean rollout, K > 1 sampled rollouts). Trained with ``logpipe train
--preset social_lstm``.

Settings, and where they come from. The paper (§3, §4): embedding 64, LSTM hidden 128, an 8 x 8 pooling grid, the
hidden states of the neighbours in a cell summed (eq. 1), the social tensor and the position embedded with ReLU and
fed together to the LSTM (eqs. 2-3), a bivariate Gaussian (mean, standard deviations, correlation) of the next
position (eq. 4) trained by its negative log-likelihood over the predicted steps (eq. 5), RMSprop with learning rate
0.003; at test the predicted positions are fed back and the neighbours' predicted hidden states pooled.

Where this deviates, and why:

* The grid's side: the paper gives 32 in its image coordinates; here 2 m, the neighbourhood of the Social-GAN
  authors' re-implementation (``neighborhood_size`` 2.0, ``grid_size`` 8 in their ``SocialPooling``), whose Social-LSTM
  figure (0.72/1.54 on ETH/UCY) is the one the tables compare with.
* The inputs and the Gaussian are over each step's displacement, not the absolute position (positions in metres
  of any scene would need a per-dataset normalisation the paper does not give); the pooling uses positions.
* Gradients clipped at norm 10 and batches of 32 windows (the paper gives neither); the schedule (``steps``,
  validation every ``val_every`` iterations on the mean forecast's ADE, ``patience``) is ours, as for Social-GAN.
* A window's agents: as in ``model.social_gan`` (``model.training.social_batch``).

Imports: core, ``model.training``, ``model.checkpoint``; never another family.
"""
