(function () {
  'use strict';
  var a = document.getElementById('return-link');
  if (!a || !a.dataset.redirectS) return;
  var s = parseFloat(a.dataset.redirectS);
  if (!(s >= 0)) return;
  setTimeout(function () { window.location.href = a.href; }, s * 1000);
})();
